"""Which CPU kernels a run's floating point comes from, and the one setting dali makes for them.

torch on x86 computes with three libraries, each picking its code path from the CPU: its own
kernels (ATEN_CPU_CAPABILITY: default, avx2, avx512), MKL for matrix products (MKL_CBWR) and
oneDNN for convolutions (ONEDNN_MAX_CPU_ISA). Another path rounds differently, so a model's
outputs move in their last bits from one CPU to another (docs/RESULTS.md, "Numerical
stability", measures how far each stage carries that).

On one machine, MKL's products may also differ from run to run: without its conditional
numerical reproducibility (CNR) mode, MKL may split a product by the alignment of its arrays in
memory, which changes from run to run. dali turns CNR on (`MKL_CBWR=AUTO,STRICT`: the CPU's own
fastest path, with the same result on every run for a given thread count) unless the user set
MKL_CBWR. It must be set before MKL starts, so `dali_cli/__init__.py` sets it when the package is
imported: torch is imported later, by the commands that need it.

Imports nothing of dali_cli; torch only inside `kernel_record`."""

from __future__ import annotations

import os
from collections.abc import Mapping

KERNEL_ENV = ("ATEN_CPU_CAPABILITY", "MKL_CBWR", "ONEDNN_MAX_CPU_ISA")


def kernel_record(environ: Mapping[str, str] = os.environ) -> dict:
    """What a manifest records of the kernel path: torch's CPU capability in use (e.g. 'AVX512')
    and each kernel setting of KERNEL_ENV present in `environ`."""
    import torch

    return {
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        **{name.lower(): environ[name] for name in KERNEL_ENV if name in environ},
    }
