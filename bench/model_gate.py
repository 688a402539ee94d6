"""Does a rebuilt model keep what the shipped one gives? The gate `make models` runs before it
replaces a model: both models evaluated on every developer set (`dali eval --model M
--scale-from M`, each at its own scale.json), then paired over the frames (`dali compare`, the
bootstrap), and the rebuilt model refused where AP_3D@0.7 (KITTI moderate) falls beyond the
noise: the 95 % interval of its paired difference lies wholly below zero on some set.

    .venv/bin/python bench/model_gate.py --shipped models/kitti-hdl64e --candidate RUN/.../model
        [--candidate-scale-from PTSN] --set drive=DATA[:GT] [--set objects_other=DATA ...]
        --work DIR --out gate.json

DATA is an imported frame set; GT its labels when not DATA's own boxes. Writes gate.json (per
set: both APs, the paired difference, its interval, the verdict) and exits 1 when the rebuilt
model is refused (`--report-only`: 0 either way, for judging a model already shipped).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DALI = ROOT / ".venv" / "bin" / "dali"
METRICS = ("3d moderate", "bev moderate", "aph moderate")
GATE_METRIC = "3d moderate"


def set_verdict(bootstrap: dict, candidate: str = "candidate") -> dict:
    """One set's line of the gate from `dali compare`'s bootstrap block (the shipped model the
    reference row): each metric's two APs, the paired difference and its 95 % interval, and
    `falls` when AP_3D's interval lies wholly below zero."""
    reference, row = bootstrap["rows"][bootstrap["reference"]], bootstrap["rows"][candidate]
    line = {"frames": bootstrap["frames"]}
    for metric in METRICS:
        if metric in row:
            line[metric] = {
                "shipped": reference[metric]["ap"],
                "candidate": row[metric]["ap"],
                "delta": row[metric]["delta"],
                "delta_interval_95": row[metric]["delta_interval_95"],
            }
    line["falls"] = line[GATE_METRIC]["delta_interval_95"][1] < 0
    return line


def gate(sets: dict[str, dict]) -> dict:
    """The verdict over every set's line (set_verdict): refused when AP_3D falls on any set."""
    fallen = [name for name, line in sets.items() if line["falls"]]
    return {"metric": f"AP_3D@0.7 {GATE_METRIC.split()[1]}", "sets": sets, "refused": bool(fallen),
            "falls_on": fallen}  # fmt: skip


def dali(*args: str, log: Path) -> None:
    with log.open("w") as out:
        done = subprocess.run([str(DALI), *args], cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
    if done.returncode:
        sys.exit(f"model_gate: dali {' '.join(args[:2])} failed ({done.returncode}); see {log}")


def compare_on(name: str, data: str, gt: str, models: dict[str, tuple], work: Path) -> dict:
    """Evaluate both models (row -> (model, its scale's directory)) on one set and compare them
    paired; compare's bootstrap block."""
    predictions = []
    for row, (model, scale_from) in models.items():
        out = work / name / row  # dali eval skips itself while its inputs are the same models
        dali("eval", "--model", str(model), "--scale-from", str(scale_from), "--data", data,
             "--gt", gt, "--protocol", "kitti", "--iou", "0.7", "--no-progress",
             "--out", str(out), log=work / f"{name}-{row}.log")  # fmt: skip
        predictions += ["--pred", f"{row}={out / 'predictions.parquet'}"]
    result = work / name / "compare.json"
    dali("compare", *predictions, "--gt", gt, "--protocol", "kitti", "--iou", "0.7",
         "--out", str(result), log=work / f"{name}-compare.log")  # fmt: skip
    return json.loads(result.read_text())["bootstrap"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shipped", type=Path, required=True, help="the model shipped now")
    parser.add_argument("--candidate", type=Path, required=True, help="the rebuilt model")
    parser.add_argument("--candidate-scale-from", type=Path,
                        help="the ptsn-sweep of the rebuilt model's scale (default: its own)")  # fmt: skip
    parser.add_argument("--set", action="append", required=True, metavar="NAME=DATA[:GT]")
    parser.add_argument("--work", type=Path, required=True, help="its evaluations go here")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--report-only", action="store_true", help="exit 0 even when refused")
    parser.add_argument("--note", help="what the shipped model is, when not the model of the same "
                        "name (e.g. another model's direct transfer); the card prints it")  # fmt: skip
    args = parser.parse_args(argv)
    models = {
        "shipped": (args.shipped, args.shipped),
        "candidate": (args.candidate, args.candidate_scale_from or args.candidate),
    }
    for model, scale_from in models.values():
        if not (model / "model.pt").is_file() or not (scale_from / "scale.json").is_file():
            parser.error(f"{model} is not a model with a scale.json in {scale_from}")
    args.work.mkdir(parents=True, exist_ok=True)
    sets = {}
    for pair in args.set:
        name, _, place = pair.partition("=")
        data, _, gt = place.partition(":")
        if not name or not Path(data).is_dir():
            parser.error(f"--set {pair}: expected NAME=DATA[:GT] with DATA a frame set")
        sets[name] = set_verdict(compare_on(name, data, gt or data, models, args.work))
    document = {"shipped": str(args.shipped), "candidate": str(args.candidate), **gate(sets)}
    if args.note:
        document["note"] = args.note
    staging = args.out.with_name(f".{args.out.name}.{os.getpid()}.part")
    staging.write_text(json.dumps(document, indent=1) + "\n")
    os.replace(staging, args.out)
    for name, line in sets.items():
        cell = line[GATE_METRIC]
        low, high = cell["delta_interval_95"]
        print(f"{name}: AP_3D@0.7 shipped {cell['shipped']:.1f}, candidate {cell['candidate']:.1f}, "
              f"paired delta {cell['delta']:+.1f} [{low:+.1f}, {high:+.1f}]"
              + ("  FALLS" if line["falls"] else ""))  # fmt: skip
    verdict = "refused" if document["refused"] else "passes"
    print(f"model_gate: the candidate {verdict} ({args.out})")
    return 1 if document["refused"] and not args.report_only else 0


if __name__ == "__main__":
    sys.exit(main())
