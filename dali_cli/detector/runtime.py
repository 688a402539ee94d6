"""Where a training or inference run executes: how many torch threads it uses and a record of
the machine (CPU model, device, torch version) for every training manifest."""

from __future__ import annotations

import os
import platform
from pathlib import Path

CPUINFO = Path("/proc/cpuinfo")


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask), at least 1.

    A stage that runs alone uses every one of them. The 1-minute load average is not a guide: in
    a `make` chain it still counts the stage that just finished, so a load-based choice trained
    `make demo` on 1 of 2 cores (1.7 vs 2.4 frames/s, issue 18). To share the machine, pass
    `--threads` (e.g. `TRAIN_FLAGS="--threads 1"` for `make -j2` on two cores).
    """
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def training_threads(requested: int | None, local_processes: int = 1) -> int:
    """torch threads for a run: `requested` (>= 1) when given, else this process's share of the
    available cores: all of them alone, cores // local_processes (at least 1) when torchrun starts
    `local_processes` ranks on this machine (LOCAL_WORLD_SIZE), so they do not oversubscribe it."""
    if requested is not None and requested < 1:
        raise ValueError(f"threads must be >= 1, got {requested}")
    if requested is not None:
        return requested
    return max(1, available_cores() // max(1, local_processes))


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


def runtime_info(threads: int, device=None, world=None) -> dict:
    """What a training manifest records about the run's machine: threads (per process), device
    (GPU model for CUDA), CPU model, available cores, torch and Python versions, and for a
    torchrun run the world size, the backend and the processes per machine."""
    import torch

    from dali_cli.device import describe

    record = {
        "threads": int(threads),
        **describe(device if device is not None else torch.device("cpu")),
        "world_size": world.size if world is not None else 1,
    }
    if world is not None and world.size > 1:
        record.update(backend=world.backend, local_world_size=world.local_size)
    return {
        **record,
        "cpu_model": cpu_model(),
        "cores_available": available_cores(),
        "torch_version": torch.__version__,
        "python_version": platform.python_version(),
    }
