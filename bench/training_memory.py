"""Training memory benchmark (not a test): peak memory of `dali pretrain` (1 epoch) through the
real CLI, the training process and its DataLoader workers together, for frame sets of
different sizes: streamed training data must hold it independent of the frame count.

The command's process tree is sampled every `--interval-s` from /proc: the sum of RSS over the
processes (counts pages shared between the training process and its forked workers once per
process: an upper bound), the sum of PSS (each shared page split between the processes that map
it: the memory the run really takes) and, inside both, the resident pages of the memory-mapped
gt-sampling database (file pages the kernel may drop and re-read). The peak of each is kept.

Usage:
  .venv/bin/python bench/training_memory.py --data 300=DIR_A --data 3000=DIR_B \
      [--loader-workers 2 (-1: a dali without the option)] [--detector-config FILE]
      [--batch-size 2] [--threads N] [--work DIR] [--label NAME] [--dali EXE --pythonpath PATH]
      [--epochs NAME=EPOCHS]
      -> bench/results/training_memory.json (one row per data set, appended by --label)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

try:
    from dali_cli.runtime.machine import available_cores, cpu_model
except ImportError:  # a checkout from before runtime.machine
    from dali_cli.detector.runtime import available_cores, cpu_model
from dali_cli.store.artifacts import FrameSet

BIN = Path(sys.executable).parent
RESULT = Path(__file__).parent / "results" / "training_memory.json"
MIB = 2**20


def process_tree(root: int) -> list[int]:
    """`root` and its descendants (pids), from /proc/*/stat parent links."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(entry.name))
    tree, todo = [], [root]
    while todo:
        pid = todo.pop()
        tree.append(pid)
        todo.extend(children.get(pid, []))
    return tree


def memory_of(pid: int) -> tuple[int, int, int]:
    """(RSS, PSS, resident gt-database pages) of one process in bytes (0s when it is gone)."""
    rss = pss = mapped = 0
    try:
        text = Path(f"/proc/{pid}/smaps").read_text()
    except OSError:
        return 0, 0, 0
    in_database = False
    for line in text.splitlines():
        if not line.split()[0].endswith(":"):  # a mapping's header line: address range, path
            in_database = "gt_database" in line
            continue
        key, value = line.split()[:2]
        if key == "Rss:":
            rss += int(value) * 1024
            mapped += int(value) * 1024 if in_database else 0
        elif key == "Pss:":
            pss += int(value) * 1024
    return rss, pss, mapped


def measure(command: list[str], interval_s: float, env: dict) -> dict:
    """Run `command`; its wall seconds and the peaks of its process tree's memory."""
    started = time.perf_counter()
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )
    peak = {"rss": 0, "pss": 0, "database": 0, "processes": 0}
    while process.poll() is None:
        pids = process_tree(process.pid)
        totals = [memory_of(pid) for pid in pids]
        peak["rss"] = max(peak["rss"], sum(t[0] for t in totals))
        peak["pss"] = max(peak["pss"], sum(t[1] for t in totals))
        peak["database"] = max(peak["database"], max((t[2] for t in totals), default=0))
        peak["processes"] = max(peak["processes"], len(pids))
        time.sleep(interval_s)
    out, err = process.communicate()
    if process.returncode != 0:
        sys.exit(f"failed: {' '.join(command)}\n{err[-4000:]}")
    return {
        "wall_s": round(time.perf_counter() - started, 1),
        "peak_rss_sum_mib": round(peak["rss"] / MIB, 1),
        "peak_pss_sum_mib": round(peak["pss"] / MIB, 1),
        "peak_gt_database_resident_mib": round(peak["database"] / MIB, 1),
        "max_processes": peak["processes"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", action="append", required=True, help="NAME=FRAMESET_DIR")
    parser.add_argument("--work", type=Path, default=Path("runs/bench_training_memory"))
    parser.add_argument("--loader-workers", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=2)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (--threads)")
    parser.add_argument("--detector-config", type=Path, default=None)
    parser.add_argument("--dali", default=str(BIN / "dali"), help="the dali executable to run")
    parser.add_argument("--label", default="streaming")
    parser.add_argument(
        "--epochs", action="append", default=[], help="NAME=EPOCHS (default 1 for each set)"
    )
    parser.add_argument("--pythonpath", default=None, help="PYTHONPATH of the dali run")
    parser.add_argument("--interval-s", type=float, default=0.2)
    args = parser.parse_args()
    rows = []
    epochs = {name: 1.0 for name in (item.split("=", 1)[0] for item in args.data)}
    epochs.update((k, float(v)) for k, v in (item.split("=", 1) for item in args.epochs))
    for item in args.data:
        name, directory = item.split("=", 1)
        frames = len(FrameSet(directory))
        out = args.work / f"{args.label}-{name}"
        command = [
            args.dali, "pretrain", "--source", directory, "--out", str(out),
            "--epochs", str(epochs[name]),
            "--batch-size", str(args.batch_size), "--device", "cpu", "--no-progress", "--force",
        ]  # fmt: skip
        if args.loader_workers >= 0:  # < 0: a dali without the option (frames in memory)
            command += ["--loader-workers", str(args.loader_workers)]
        if args.threads:
            command += ["--threads", str(args.threads)]
        if args.detector_config:
            command += ["--detector-config", str(args.detector_config)]
        load = os.getloadavg()[0]
        row = {
            "name": name, "frames": frames, "epochs": epochs[name], "data": directory,
            "load_1m_before": load,
        }  # fmt: skip
        env = dict(os.environ)
        if args.pythonpath is not None:
            env["PYTHONPATH"] = args.pythonpath
        row.update(measure(command, args.interval_s, env))
        summary = json.loads((out / "model.json").read_text())["train"]
        row.update(frames_per_s=summary["frames_per_s"], steps=summary["steps"])
        print(json.dumps(row), flush=True)
        rows.append(row)
    results = json.loads(RESULT.read_text()) if RESULT.is_file() else {"runs": {}}
    results["machine"] = {"cpu": cpu_model(), "cores_available": available_cores()}
    results["runs"][args.label] = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "command": " ".join(sys.argv),
        "loader_workers": args.loader_workers,
        "batch_size": args.batch_size,
        "detector_config": None if args.detector_config is None else str(args.detector_config),
        "rows": rows,
    }
    RESULT.parent.mkdir(parents=True, exist_ok=True)
    RESULT.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
