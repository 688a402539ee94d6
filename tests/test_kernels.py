"""The CPU kernel settings: MKL's reproducible mode is on in every dali process unless the user
chose one, and manifests record the kernel path a run computed with."""

from __future__ import annotations

import os
import subprocess
import sys

from dali_cli import MKL_CNR_MODE
from dali_cli.runtime.kernels import KERNEL_ENV, kernel_record
from dali_cli.runtime.machine import runtime_info

SHOW = "import dali_cli, os, torch; print(os.environ.get('MKL_CBWR'))"


def mkl_mode_in_a_new_process(**settings) -> str:
    env = {k: v for k, v in os.environ.items() if k not in KERNEL_ENV}
    env.update(settings)
    done = subprocess.run([sys.executable, "-c", SHOW], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_importing_dali_turns_on_mkls_reproducible_mode():
    assert mkl_mode_in_a_new_process() == MKL_CNR_MODE == "AUTO,STRICT"


def test_a_users_own_mkl_mode_is_kept():
    assert mkl_mode_in_a_new_process(MKL_CBWR="COMPATIBLE") == "COMPATIBLE"


def test_the_record_names_the_kernel_path_and_only_the_settings_present():
    import torch

    record = kernel_record({"ATEN_CPU_CAPABILITY": "avx2", "PATH": "/bin"})
    assert record == {
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "aten_cpu_capability": "avx2",
    }
    assert runtime_info(1)["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert runtime_info(1)["mkl_cbwr"] == os.environ["MKL_CBWR"]
