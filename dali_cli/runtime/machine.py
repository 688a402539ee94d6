"""Where a training or inference run executes: how many torch threads it uses and a record of
the machine (CPU model, device, torch version) for every training and inference manifest.

Imports nothing of dali_cli but `runtime.cores` and `runtime.kernels`; torch is imported inside the functions."""

from __future__ import annotations

import platform
from pathlib import Path

from dali_cli.runtime.cores import available_cores
from dali_cli.runtime.kernels import kernel_record

CPUINFO = Path("/proc/cpuinfo")


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
    (GPU model for CUDA), CPU model, the CPU kernel path (runtime/kernels.py), available cores,
    torch and Python versions, and for a torchrun run the world size, the backend and the
    processes per machine."""
    import torch

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
        **kernel_record(),
        "cores_available": available_cores(),
        "torch_version": torch.__version__,
        "python_version": platform.python_version(),
    }


def describe(device) -> dict:
    """What a manifest records about the device: its name, and for CUDA the GPU model, its memory
    and the number of GPUs this process sees."""
    import torch

    record = {"device": str(device)}
    if device.type == "cuda":
        properties = torch.cuda.get_device_properties(device)
        record.update(
            gpu_model=properties.name,
            gpu_memory_gib=round(properties.total_memory / 2**30, 1),
            gpu_count=torch.cuda.device_count(),
            cuda_version=torch.version.cuda,
        )
    return record
