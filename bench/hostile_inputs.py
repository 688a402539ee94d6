"""Probe `dali` with hostile inputs as separate processes, the way a user's shell meets them.

Each case builds its input in a scratch directory, runs one `dali` command with a time limit and
sorts the outcome: `ok` (refused with exit 1 or 2, one-line error, nothing written, ≤ 1 s beyond
the command's start-up), `hang` (over the limit), `traceback`, `exit-0` (accepted what it should
refuse), `slow` (refused after more than a second of reading) or `data-loss` (a file the user
owns changed). The cases are the classes of docs/input-validation.md: every reader fed a FIFO, a
directory, a dangling link, /dev/zero, a 4 GiB sparse file, JSON nested 200,000 deep or random
bytes; artifact values beyond the options' kinds; imports outside the frame-set contract; eval's
scoring of unscorable predictions and its keeping of a user's files.

    .venv/bin/python bench/hostile_inputs.py [--limit-s 20] [--only WORD]

Prints a line per case and the counts per outcome; exit 1 when any case is not `ok`.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the bad files the fuzz tests use too
from hostile_files import BAD_KINDS, box_table_with, make_bad  # noqa: E402

DALI = str(Path(sys.executable).with_name("dali"))
MODEL = ROOT / "models" / "kitti-hdl64e"
KITTI = ROOT / "tests" / "fixtures" / "real" / "kitti"
REFUSAL_S = 1.0


def run(args: list, limit_s: float) -> tuple[int | None, str, float]:
    """(exit code or None on a hang, stdout + stderr, seconds) of `dali ARGS`."""
    started = time.perf_counter()
    try:
        done = subprocess.run([DALI, *map(str, args)], capture_output=True, text=True,
                              timeout=limit_s, stdin=subprocess.DEVNULL)  # fmt: skip
        return done.returncode, done.stdout + done.stderr, time.perf_counter() - started
    except subprocess.TimeoutExpired as expired:
        text = (expired.stdout or b"").decode(errors="replace") if expired.stdout else ""
        return None, text, time.perf_counter() - started


def startup_s() -> float:
    """Seconds a stage spends before it reads its first input: starting Python and importing
    the detector (torch), best of three."""
    code = "import dali_cli.cli, dali_cli.detector.model"
    best = float("inf")
    for _ in range(3):
        started = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], check=True)
        best = min(best, time.perf_counter() - started)
    return best


class Probe:
    def __init__(self, scratch: Path, limit_s: float):
        self.scratch, self.limit_s, self.rows = scratch, limit_s, []
        self.base_s = startup_s()
        self.frames = scratch / "frames"
        code, text, _ = run(["import", "kitti", KITTI, "--no-progress", "--out", self.frames], 120)
        assert code == 0, text
        self.count = 0

    def fresh(self) -> Path:
        self.count += 1
        path = self.scratch / f"case{self.count}"
        path.mkdir()
        return path

    def refuse(self, name: str, args: list, out: Path | None = None, owned: Path | None = None,
               owned_bytes: bytes | None = None) -> None:  # fmt: skip
        code, text, seconds = run(args, self.limit_s)
        if code is None:
            outcome = "hang"
        elif "Traceback" in text:
            outcome = "traceback"
        elif owned is not None and (not owned.exists() or owned.read_bytes() != owned_bytes):
            outcome = "data-loss"
        elif code == 0:
            outcome = "exit-0"
        elif out is not None and os.path.lexists(out):
            outcome = "wrote-partial"
        elif seconds - self.base_s > REFUSAL_S:
            outcome = "slow"
        else:
            outcome = "ok"
        last = text.strip().splitlines()[-1] if text.strip() else ""
        self.rows.append((outcome, name, seconds, last[:110]))
        print(f"{outcome:13s} {seconds:6.2f} s  {name}  | {last[:100]}", flush=True)

    def model(self, case: Path) -> Path:
        model = case / "model"
        shutil.copytree(MODEL, model)
        return model

    def kitti_root(self, case: Path) -> Path:
        root = case / "kitti"
        shutil.copytree(KITTI, root)
        return root

    def box_table(self, case: Path, changes: dict) -> Path:
        """The frame set's box table with columns replaced: {name: one value for every row}."""
        return box_table_with(self.frames, case / "boxes.parquet", **changes)


def reader_cases(probe: Probe) -> None:
    for kind in BAD_KINDS:
        for name in ("model.json", "scale.json", "model.pt"):
            for command in ("eval", "ptsn-sweep", "pseudo-label"):
                if command == "ptsn-sweep" and name == "scale.json":
                    continue  # a sweep makes a scale; it does not read the model's
                case = probe.fresh()
                model = probe.model(case)
                make_bad(model / name, kind)
                out = case / "out"
                args = [command, "--model", model, "--data", probe.frames, "--no-progress", "--out",
                        out]  # fmt: skip
                if command == "pseudo-label" or name == "scale.json":
                    args += ["--scale-from", model]
                probe.refuse(f"{command}: {name} is {kind}", args, out)
        case = probe.fresh()
        make_bad(case / "cfg.json", kind)
        probe.refuse(f"pretrain: --detector-config is {kind}",
                     ["pretrain", "--source", probe.frames, "--detector-config", case / "cfg.json",
                      "--out", case / "out"], case / "out")  # fmt: skip
        case = probe.fresh()
        make_bad(case / "s.toml", kind)
        probe.refuse(f"synth: --sensors is {kind}",
                     ["synth", "--sensors", case / "s.toml", "--frames", "1", "--out", case / "out"],
                     case / "out")  # fmt: skip
        for relative in ("frames.zarr/points/zarr.json", "frames.zarr/zarr.json", "boxes.parquet"):
            case = probe.fresh()
            frames = case / "frames"
            shutil.copytree(probe.frames, frames)
            make_bad(frames / relative, kind)
            probe.refuse(
                f"view: {relative} is {kind}",
                ["view", frames, "--frame", "0", "--out", case / "v.png"],
                case / "v.png",
            )
        case = probe.fresh()
        make_bad(case / "f.png", kind)
        if kind in ("fifo", "dangling", "dev-zero", "dev-null", "directory"):
            probe.refuse(
                f"view: --out is {kind}",
                ["view", probe.frames, "--frame", "0", "--out", case / "f.png"],
            )
        for sub in ("label_2", "calib", "velodyne", "ids"):
            case = probe.fresh()
            root = probe.kitti_root(case)
            args = ["import", "kitti", root, "--no-progress", "--out", case / "out"]
            if sub == "ids":
                make_bad(case / "ids.txt", kind)
                args += ["--ids", case / "ids.txt"]
            else:
                first = sorted((root / "training" / sub).iterdir())[0]
                make_bad(first, kind)
            probe.refuse(f"import kitti: {sub} file is {kind}", args, case / "out")


def value_cases(probe: Probe) -> None:
    hostile_scale = {
        "scale": [1e-300, 1e308, "1.2", -1, None],
        "E_est": [[0, 0, 0], [float("nan"), 1, 1], [4, 1.6], "big", [1e308, 1, 1]],
    }
    for field, values in hostile_scale.items():
        for value in values:
            for command in ("eval", "pseudo-label"):
                case = probe.fresh()
                model = probe.model(case)
                document = json.loads((model / "scale.json").read_text())
                document[field] = value
                (model / "scale.json").write_text(json.dumps(document))
                probe.refuse(f"{command}: scale.json {field} = {value!r}",
                             [command, "--model", model, "--data", probe.frames, "--scale-from", model,
                              "--no-progress", "--out", case / "out"], case / "out")  # fmt: skip
    case = probe.fresh()
    model = probe.model(case)
    document = json.loads((model / "model.json").read_text())
    document["detector"] = "nosuch"
    (model / "model.json").write_text(json.dumps(document))
    probe.refuse("eval: model.json detector = 'nosuch'",
                 ["eval", "--model", model, "--data", probe.frames, "--no-progress", "--out",
                  case / "out"], case / "out")  # fmt: skip
    case = probe.fresh()
    probe.refuse("ptsn-sweep --target-size 1e308,1,1",
                 ["ptsn-sweep", "--model", MODEL, "--data", probe.frames, "--target-size",
                  "1e308,1,1", "--out", case / "out"], case / "out")  # fmt: skip
    case = probe.fresh()
    probe.refuse("export kitti --image-size 99999999999x99999999999",
                 ["export", "kitti", probe.frames, "--image-size", "99999999999x99999999999",
                  "--out", case / "out"], case / "out")  # fmt: skip
    changes = {
        "l = 1e308": {"l": 1e308},
        "frame_id not in the frame set": {"frame_id": "nosuch"},
        "l = NaN": {"l": float("nan")},
        "h = -1": {"h": -1.0},
    }
    for label, change in changes.items():
        case = probe.fresh()
        frames = case / "frames"
        shutil.copytree(probe.frames, frames)
        probe.box_table(case, change).replace(frames / "boxes.parquet")
        probe.refuse(
            f"view: boxes.parquet with {label}",
            ["view", frames, "--frame", "0", "--out", case / "v.png"],
            case / "v.png",
        )
        probe.refuse(
            f"export openpcdet: boxes.parquet with {label}",
            ["export", "openpcdet", frames, "--out", case / "out"],
            case / "out",
        )
    scoring = {
        "scores all -1": {"score": -1.0},
        "lengths all 0": {"l": 0.0, "score": 0.9},
        "frame_ids missing from --gt": {"frame_id": "nosuch", "score": 0.9},
    }
    for label, change in scoring.items():
        case = probe.fresh()
        pred = probe.box_table(case, change)
        probe.refuse(f"eval --pred whose {label}",
                     ["eval", "--pred", pred, "--gt", probe.frames, "--out", case / "m.json"],
                     case / "m.json")  # fmt: skip


def import_cases(probe: Probe) -> None:
    readme = (ROOT / "README.md").read_bytes()
    contents = {
        "intensity -5": lambda p: p * np.array([1, 1, 1, 0], np.float32) - [0, 0, 0, 5],
        "intensity 1e9": lambda p: p * np.array([1, 1, 1, 0], np.float32) + [0, 0, 0, 1e9],
        "ASCII text as floats": lambda p: np.frombuffer(readme[: len(readme) // 16 * 16], "<f4"),
        "all zeros": lambda p: np.zeros_like(p),
        "coordinates 1e6 m": lambda p: p * np.array([1e6, 1, 1, 1], np.float32),
    }
    for label, content in contents.items():
        case = probe.fresh()
        root = probe.kitti_root(case)
        scan = sorted((root / "training" / "velodyne").glob("*.bin"))[0]
        points = np.fromfile(scan, "<f4").reshape(-1, 4)
        np.asarray(content(points), "<f4").tofile(scan)
        probe.refuse(f"import kitti: a scan with {label}",
                     ["import", "kitti", root, "--no-progress", "--out", case / "out"],
                     case / "out")  # fmt: skip
    case = probe.fresh()
    (case / "ids.txt").write_text("")
    probe.refuse("import kitti: an empty --ids file",
                 ["import", "kitti", KITTI, "--ids", case / "ids.txt", "--no-progress", "--out",
                  case / "out"], case / "out")  # fmt: skip


def keeping_cases(probe: Probe) -> None:
    """eval never replaces a file it did not write, in each --out form."""
    for form in ("DIR", "DIR/metrics.json"):
        case = probe.fresh()
        mine = case / "mine"
        mine.mkdir()
        shutil.copy(probe.frames / "boxes.parquet", mine / "predictions.parquet")
        owned = mine / "predictions.parquet"
        before = owned.read_bytes()
        out = mine if form == "DIR" else mine / "metrics.json"
        run(["eval", "--pred", owned, "--gt", probe.frames, "--out", mine / "metrics.json"], 60)
        code, text, seconds = run(["eval", "--model", MODEL, "--data", probe.frames,
                                   "--no-progress", "--out", out], probe.limit_s)  # fmt: skip
        changed = not owned.exists() or owned.read_bytes() != before
        outcome = "data-loss" if changed else ("ok" if code not in (0, None) else "exit-0")
        last = text.strip().splitlines()[-1] if text.strip() else ""
        probe.rows.append((outcome, f"eval --model --out {form} beside a user's predictions",
                           seconds, last))  # fmt: skip
        print(f"{outcome:13s} {seconds:6.2f} s  eval --out {form} beside a user's predictions"
              f"  | {last[:100]}")  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--limit-s", type=float, default=20.0, help="a case over this is a hang")
    parser.add_argument("--only", default="", help="run only the groups whose name has this word")
    options = parser.parse_args()
    groups = {"readers": reader_cases, "values": value_cases, "imports": import_cases,
              "keeping": keeping_cases}  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="dali-hostile-") as scratch:
        probe = Probe(Path(scratch), options.limit_s)
        print(f"start-up of a refusal that reads nothing: {probe.base_s:.2f} s")
        for name, group in groups.items():
            if options.only in name:
                group(probe)
    outcomes = {}
    for outcome, *_ in probe.rows:
        outcomes[outcome] = outcomes.get(outcome, 0) + 1
    print(f"{len(probe.rows)} cases: " + ", ".join(f"{k} {v}" for k, v in sorted(outcomes.items())))
    return 0 if set(outcomes) <= {"ok"} else 1


if __name__ == "__main__":
    sys.exit(main())
