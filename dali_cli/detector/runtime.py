"""Where a training or inference run executes: how many torch threads it uses and a record of
the machine (CPU model, device, torch version) for every training manifest."""

from __future__ import annotations

import platform
from pathlib import Path

from dali_cli.cores import available_cores

CPUINFO = Path("/proc/cpuinfo")


def training_threads(requested: int | None) -> int:
    """torch threads for a run: `requested` (>= 1) when given, else every available core."""
    if requested is not None and requested < 1:
        raise ValueError(f"threads must be >= 1, got {requested}")
    return requested if requested is not None else available_cores()


def cpu_model(cpuinfo: Path = CPUINFO) -> str:
    """The CPU's model name ('AMD EPYC 7B13', ...) from /proc/cpuinfo, else platform's guess."""
    try:
        for line in cpuinfo.read_text(errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() in ("model name", "Processor", "cpu model") and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def runtime_info(threads: int) -> dict:
    """What a training manifest records about the run's machine: threads, device, CPU model,
    available cores, torch and Python versions."""
    import torch

    return {
        "threads": int(threads),
        "device": "cpu",
        "cpu_model": cpu_model(),
        "cores_available": available_cores(),
        "torch_version": torch.__version__,
        "python_version": platform.python_version(),
    }
