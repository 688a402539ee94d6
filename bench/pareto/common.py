"""What every benchmark records with a timing: the machine, its load, the threads used, repeats.

The machine these numbers come from is usually shared (other jobs run beside the benchmark), so
every timing is a median over repeats and carries the load average before and after it.
"""

from __future__ import annotations

import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Callable

import numpy as np


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux), else platform.processor()."""
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def load_average() -> list[float] | None:
    """1, 5 and 15 minute load averages, rounded; None where the OS has none."""
    return [round(v, 2) for v in os.getloadavg()] if hasattr(os, "getloadavg") else None


def machine(threads: int) -> dict:
    """The record of where and how a benchmark ran (threads: what the timed code may use)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 1
    return {
        "cpu": cpu_model(),
        "logical_cpus": os.cpu_count(),
        "cores_available": cores,
        "threads_used": threads,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "shared_machine": True,
    }


def pin_one_core() -> None:
    """Run this process (and threads it starts later) on one core, where the OS allows it."""
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})


def best_seconds(function: Callable[[], object], repeats: int) -> float:
    """The fastest wall time (seconds) of `repeats` runs of `function`."""
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        times.append(time.perf_counter() - started)
    return min(times)


def timed(function: Callable[[], object], repeats: int) -> dict:
    """Run `function` `repeats` times: median and min of wall and CPU seconds, and all walls."""
    walls, cpus = [], []
    for _ in range(max(1, repeats)):
        wall, cpu = time.perf_counter(), time.process_time()
        function()
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    return {
        "seconds_median": float(np.median(walls)),
        "seconds_min": float(np.min(walls)),
        "cpu_seconds_median": float(np.median(cpus)),
        "repeats": len(walls),
        "all_seconds": [round(w, 6) for w in walls],
    }


def dali(*arguments) -> str:
    """Run `dali ARGUMENTS` in this Python (echoed on stderr; a failure raises); the command
    line as shown."""
    shown = "dali " + " ".join(shlex.quote(str(a)) for a in arguments)
    print(f"$ {shown}", file=sys.stderr, flush=True)
    subprocess.run([sys.executable, "-m", "dali_cli.cli", *map(str, arguments)], check=True)
    return shown
