"""Crash and disk-full probe of every writing stage (docs/data-safety.md).

crash: each stage killed with SIGKILL at each step of its commit (the temporary directory
created but not marked, the old artifact marked, exchanged, unmarked, the replaced artifact
emptied before its marker is removed; the two-rename path's retired/renamed) and by a timer at
10/50/90% of its run, on a fresh --out and while replacing a good artifact, every start in a
fresh PID namespace (`unshare -pf`: the same pid each time, as in a container restart); then
the same command again. Counted: reruns that refuse or fail, remnants beside --out after a
successful rerun, tracebacks, good artifacts lost (an `--out` that held one and, after the
kill, holds no complete one nor a recoverable retired copy).

disk: each stage with --out on a tmpfs of each size (a private mount namespace, `unshare -m`).
Counted: tracebacks, failures whose message does not name --out, remnants (a lock, a
temporary) beside a failed or finished --out, exit codes other than 0/1.

Needs root (unshare, mount). Usage:
    python bench/crash_probe.py --mode crash|disk|both [--stages synth,pretrain,...] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DALI = [sys.executable, "-m", "dali_cli.cli"]
SMALL = {"x_range_m": [0.0, 25.6], "y_range_m": [-12.8, 12.8], "pfn_channels": 8,
         "block_channels": [8, 16, 16], "block_layers": [1, 1, 1], "up_channels": 8}  # fmt: skip
STEPS = ["created", "marked", "exchanged", "unmarked", "emptied", "retired", "renamed"]
TIMERS = [0.1, 0.5, 0.9]
SIZES = ["200k", "1m", "4m", "10m", "20m"]
# a dali start whose after_step SIGKILLs it at the step named in DALI_PROBE_KILL_AT; with
# DALI_PROBE_TWO_RENAMES the exchange is unavailable (the fallback's steps)
HOOKED = """
import os, signal, sys
from dali_cli.store import atomic_dir
step = os.environ.get("DALI_PROBE_KILL_AT")
if os.environ.get("DALI_PROBE_TWO_RENAMES"):
    atomic_dir._exchange = lambda a, b: False
def after_step(name):
    if name == step:
        os.kill(os.getpid(), signal.SIGKILL)
atomic_dir.after_step = after_step
from dali_cli.cli import main
sys.argv[0] = "dali"
main()
"""


def stage_args(world: Path, stage: str, out: Path) -> list[str]:
    w = {k: str(world / k) for k in ("source", "target", "model", "library", "pseudo", "reg")}
    kitti = str(ROOT / "tests" / "fixtures" / "real" / "kitti")
    table = {
        "synth": ["synth", "--sensor", "kitti", "--frames", "2", "--seed", "3"],
        "import-kitti": ["import", "kitti", kitti],
        "pretrain": ["pretrain", "--source", w["source"], "--epochs", "1", "--no-progress",
                     "--detector-config", str(world / "detector.json")],
        "retrain": ["retrain", "--init", w["model"], "--source", w["source"], "--ppcg",
                    w["target"], "--epochs", "1", "--no-progress", "--target-profile", "kitti"],
        "eval-model": ["eval", "--model", w["model"], "--data", w["target"], "--scale", "1",
                       "--no-progress"],
        "ptsn-sweep": ["ptsn-sweep", "--model", w["model"], "--data", w["target"],
                       "--no-progress"],
        "pseudo-label": ["pseudo-label", "--model", w["model"], "--data", w["target"],
                         "--scale", "1", "--no-progress"],
        "ppcg-rc": ["ppcg-rc", "--data", w["target"], "--boxes", w["target"], "--library",
                    w["library"], "--no-progress"],
        "ppcg-cf": ["ppcg-cf", "--data", w["target"], "--boxes", w["target"], "--library",
                    w["library"], "--no-progress"],
        "export-kitti": ["export", "kitti", str(world / "kitti-set"), "--calib-root", kitti],
        "register": ["register", "--data", w["target"], "--no-progress"],
        "track-pseudo": ["track-pseudo", "--pseudo", w["pseudo"], "--data", w["target"],
                         "--poses", w["reg"]],
        "library-build": ["library", "build", "--procedural", "2"],
    }  # fmt: skip
    return [*table[stage], "--out", str(out)]


STAGES = ["synth", "import-kitti", "pretrain", "retrain", "eval-model", "ptsn-sweep",
          "pseudo-label", "ppcg-rc", "ppcg-cf", "export-kitti", "register", "track-pseudo",
          "library-build"]  # fmt: skip


def run(
    args: list[str], env: dict | None = None, prefix: list[str] = (), timeout=600, kill_after=None
):
    """(exit code, stderr+stdout, seconds) of `prefix + args`; `kill_after` s: SIGKILL then."""
    environment = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    started = time.perf_counter()
    process = subprocess.Popen([*prefix, *args], env=environment, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True, start_new_session=True)  # fmt: skip
    try:
        output, _ = process.communicate(timeout=kill_after or timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        output, _ = process.communicate()
    return process.returncode, output, time.perf_counter() - started


def build_world(world: Path) -> None:
    """Tiny inputs for every stage (made once)."""
    if (world / "done").exists():
        return
    shutil.rmtree(world, ignore_errors=True)
    world.mkdir(parents=True)
    (world / "detector.json").write_text(json.dumps(SMALL))
    steps = [
        ["synth", "--sensor", "waymo", "--frames", "2", "--seed", "1", "--out", world / "source"],
        ["synth", "--sensor", "kitti", "--frames", "2", "--seed", "2", "--out", world / "target"],
        ["pretrain", "--source", world / "source", "--epochs", "1", "--no-progress",
         "--detector-config", world / "detector.json", "--out", world / "model"],
        ["library", "build", "--procedural", "2", "--out", world / "library"],
        ["pseudo-label", "--model", world / "model", "--data", world / "target", "--scale", "1",
         "--score-min", "0.01", "--no-progress", "--out", world / "pseudo"],
        ["register", "--data", world / "target", "--no-progress", "--out", world / "reg"],
        ["import", "kitti", ROOT / "tests" / "fixtures" / "real" / "kitti", "--out",
         world / "kitti-set"],
    ]  # fmt: skip
    for step in steps:
        code, output, _ = run([*DALI, *map(str, step)])
        if code != 0:
            raise SystemExit(f"crash_probe: could not build the inputs: {step}\n{output}")
    (world / "done").write_text("")


def complete(out: Path) -> bool:
    try:
        return json.loads((out / "manifest.json").read_text()).get("stage") is not None
    except (OSError, ValueError):
        return False


def crash_case(world, work, stage, replacing, kill, baseline_s, counts, failures):
    """One kill then one rerun, both in fresh PID namespaces."""
    case = work / f"{stage}-{'replace' if replacing else 'fresh'}-{kill}"
    shutil.rmtree(case, ignore_errors=True)
    case.mkdir(parents=True)
    out = case / "out"
    namespace = ["unshare", "-pf", "--mount-proc"]
    if replacing:
        shutil.copytree(work / "good" / stage, out, symlinks=True)
    args = stage_args(world, stage, out) + (["--force"] if replacing else [])
    env, kill_after = {}, None
    if isinstance(kill, float):
        kill_after = max(0.2, baseline_s * kill)
    else:
        env["DALI_PROBE_KILL_AT"] = kill
        if kill in ("retired", "renamed") or kill.endswith("2r"):
            env["DALI_PROBE_TWO_RENAMES"] = "1"
    code, output, _ = run([sys.executable, "-c", HOOKED, *args], env, namespace,
                          kill_after=kill_after)  # fmt: skip
    counts["kills"] += 1
    if "Traceback" in output:
        counts["tracebacks"] += 1
        failures.append((case.name, "traceback in the killed run", output[-400:]))
    if replacing and not complete(out) and not any(complete(p) for p in case.glob("out.old-*")):
        counts["lost"] += 1
        failures.append((case.name, "good artifact lost", sorted(p.name for p in case.iterdir())))
    code, output, _ = run([*DALI, *stage_args(world, stage, out)], None, namespace)
    counts["reruns"] += 1
    if "Traceback" in output:
        counts["tracebacks"] += 1
    if code != 0:
        counts["rerun_failed"] += 1
        failures.append((case.name, f"rerun exit {code}", output[-400:]))
        return
    left = sorted(p.name for p in case.iterdir() if p.name != "out")
    if left:
        counts["remnants"] += 1
        failures.append((case.name, "remnants", left))


def probe_crash(world: Path, work: Path, stages: list[str]) -> dict:
    counts = dict.fromkeys(["kills", "reruns", "rerun_failed", "remnants", "tracebacks", "lost"], 0)
    failures = []
    (work / "good").mkdir(parents=True, exist_ok=True)
    for stage in stages:
        good = work / "good" / stage
        shutil.rmtree(good, ignore_errors=True)
        code, output, seconds = run([*DALI, *stage_args(world, stage, good)])
        if code != 0:
            failures.append((stage, "baseline failed", output[-400:]))
            continue
        for replacing in (False, True):
            steps = STEPS if replacing else ["created", "renamed"]
            for kill in [*TIMERS, *steps]:
                crash_case(world, work, stage, replacing, kill, seconds, counts, failures)
        print(f"crash {stage}: {json.dumps(counts)}", flush=True)
    return {"counts": counts, "failures": failures}


def probe_disk(world: Path, work: Path, stages: list[str]) -> dict:
    counts = dict.fromkeys(["runs", "ok", "clean_errors", "unnamed", "remnants", "tracebacks",
                            "bad_exit"], 0)  # fmt: skip
    failures = []
    for stage in stages:
        for size in SIZES:
            mount = work / f"disk-{stage}-{size}"
            shutil.rmtree(mount, ignore_errors=True)
            mount.mkdir(parents=True)
            out = mount / "out"
            script = (f"mount -t tmpfs -o size={size} tmpfs {mount} && "
                      + " ".join(map(repr_arg, [*DALI, *stage_args(world, stage, out)]))
                      + f"; code=$?; echo; echo LISTING $(ls -A {mount}); exit $code")  # fmt: skip
            code, output, _ = run(["sh", "-c", script], None, ["unshare", "-m"])
            counts["runs"] += 1
            listing = output.rsplit("LISTING", 1)[-1].split()
            text = output.rsplit("LISTING", 1)[0]
            if "Traceback" in text:
                counts["tracebacks"] += 1
                failures.append((mount.name, "traceback", text[-600:]))
            if code == 0:
                counts["ok"] += 1
                if listing != ["out"]:
                    counts["remnants"] += 1
                    failures.append((mount.name, "remnants after success", listing))
            elif code == 1:
                counts["clean_errors"] += 1
                if str(out) not in text:
                    counts["unnamed"] += 1
                    failures.append((mount.name, "error does not name --out", text[-300:]))
                if listing:
                    counts["remnants"] += 1
                    failures.append((mount.name, "remnants after failure", listing))
            else:
                counts["bad_exit"] += 1
                failures.append((mount.name, f"exit {code}", text[-300:]))
            shutil.rmtree(mount, ignore_errors=True)
        print(f"disk {stage}: {json.dumps(counts)}", flush=True)
    return {"counts": counts, "failures": failures}


def repr_arg(arg) -> str:
    return "'" + str(arg).replace("'", "'\\''") + "'"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", choices=["crash", "disk", "both"], required=True)
    parser.add_argument("--stages", default=",".join(STAGES))
    parser.add_argument("--work", type=Path, default=Path("runs/crash-probe"))
    args = parser.parse_args(argv)
    stages = [s for s in args.stages.split(",") if s]
    unknown = sorted(set(stages) - set(STAGES))
    if unknown:
        parser.error(f"unknown stages: {', '.join(unknown)} (known: {', '.join(STAGES)})")
    world = args.work / "world"
    build_world(world)
    report = {}
    if args.mode in ("crash", "both"):
        report["crash"] = probe_crash(world, args.work / "crash", stages)
    if args.mode in ("disk", "both"):
        report["disk"] = probe_disk(world, args.work / "disk", stages)
    for mode, result in report.items():
        print(f"{mode}: {json.dumps(result['counts'])}")
        for failure in result["failures"][:40]:
            print(f"  {mode} FAIL {failure}")
    bad = sum(len(r["failures"]) for r in report.values())
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
