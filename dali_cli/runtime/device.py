"""Which torch device a training or inference run uses: `--device auto|cpu|cuda|cuda:N` resolved
to a `torch.device` (with a clear error when it does not exist), bf16 autocast on it, and a
record of the device (GPU model, count) for the manifest.

torch is imported inside the functions, so `dali --help` stays fast.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Callable
from typing import TypedDict

from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.runtime.machine import runtime_info

DEVICE_SPECS = "auto, cpu, cuda or cuda:N"
PRECISIONS = ("fp32", "bf16")


class DeviceError(StageError):
    """A device that was asked for but is not there (exit 1, before anything is written)."""


def parse_device_spec(spec: str) -> tuple[str, int | None]:
    """'auto' | 'cpu' | 'cuda' | 'cuda:N' -> (kind, index or None); ParameterError (field `device`) otherwise."""
    text = str(spec).strip().lower()
    if text in ("auto", "cpu", "cuda"):
        return text, None
    match = re.fullmatch(r"cuda:(\d+)", text)
    if match:
        return "cuda", int(match.group(1))
    raise ParameterError("device", f"'{spec}' is not a device; use {DEVICE_SPECS}")


def resolve_device(spec: str = "auto", local_rank: int | None = None):
    """The torch.device for `spec`.

    auto: CUDA when torch.cuda.is_available(), else the CPU. cuda without an index: the GPU of
    this process's local rank under torchrun (`local_rank`), else GPU 0. A CUDA device that does
    not exist is a DeviceError naming what is there, raised before any output is written.
    """
    import torch

    kind, index = parse_device_spec(spec)
    if kind == "auto":
        kind = "cuda" if torch.cuda.is_available() else "cpu"
    if kind == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise DeviceError(
            f"--device {spec}: no CUDA GPU is available to this process (torch "
            f"{torch.__version__}, built with CUDA {torch.version.cuda or 'none'}); "
            "use --device cpu or --device auto"
        )
    count = torch.cuda.device_count()
    if index is None:
        index = local_rank if local_rank is not None else 0
    if not 0 <= index < count:
        raise DeviceError(
            f"--device {spec}: GPU {index} does not exist (this process sees {count}: "
            f"cuda:0..cuda:{count - 1}; check CUDA_VISIBLE_DEVICES and --nproc-per-node)"
        )
    return torch.device("cuda", index)


def check_precision(precision: str, device) -> None:
    """bf16 needs a device that runs it: any CPU (slow without AMX / AVX512-BF16), a CUDA GPU
    with bf16 support (Ampere or newer)."""
    import torch

    if precision not in PRECISIONS:
        raise ParameterError("precision", f"'{precision}' is not one of {', '.join(PRECISIONS)}")
    if precision == "bf16" and device.type == "cuda" and not torch.cuda.is_bf16_supported():
        raise DeviceError(
            f"--precision bf16: {torch.cuda.get_device_name(device)} does not support bf16; "
            "use --precision fp32"
        )


class InferenceOptions(TypedDict, total=False):
    """How an inference stage (ptsn-sweep, pseudo-label) runs the detector: `device` (auto |
    cpu | cuda | cuda:N, default auto), `precision` (fp32 | bf16, default fp32), `batch_size`
    frames per forward pass (default 8), `threads` torch threads (default: every core this
    process may use, as training), `progress` (a bar, default True) and, for tests,
    `detector_loader(model_dir)` in place of the stage's own loader."""

    device: str
    precision: str
    batch_size: int
    threads: int | None
    progress: bool
    detector_loader: Callable | None


def check_options(options: dict, typed: type, where: str) -> None:
    """A TypeError naming the first keyword of `options` that the TypedDict `typed` does not
    declare: keyword options collected with **kwargs stay as strict as named parameters."""
    unknown = sorted(set(options) - set(typed.__annotations__))
    if unknown:
        raise TypeError(f"{where}() got an unexpected keyword argument '{unknown[0]}'")


def inference_setup(inference: dict, where: str):
    """(torch.device, precision) of an inference stage's InferenceOptions `inference` (unknown
    keywords a TypeError naming `where`; a missing GPU or an unsupported precision an error
    before anything is written)."""
    check_options(inference, InferenceOptions, where)
    set_inference_threads(inference.get("threads"))
    precision = inference.get("precision", "fp32")
    return inference_device(inference.get("device", "auto"), precision), precision


def set_inference_threads(requested: int | None = None) -> int:
    """Give torch `requested` threads, else every core this process may use (training's rule,
    runtime.machine.training_threads), and return the count. Set, not left to torch's default:
    that follows OMP_NUM_THREADS / MKL_NUM_THREADS (a shell's, a Ray worker's) and physical cores
    on SMT machines, and the thread count decides the float sums, so the boxes' last bits."""
    import torch

    from dali_cli.runtime.machine import training_threads

    threads = training_threads(requested)
    torch.set_num_threads(threads)
    return threads


def inference_device(spec: str, precision: str):
    """The torch.device an inference stage runs on, with its precision checked (both before the
    stage writes anything)."""
    device = resolve_device(spec)
    check_precision(precision, device)
    return device


def place(predictor, device, precision: str = "fp32"):
    """`predictor` on `device` with `precision`: a Detector is moved there (`Detector.to`); other
    predictors (stand-ins that only `predict`) are returned as they are."""
    move = getattr(predictor, "to", None)
    return move(device, precision) if callable(move) else predictor


def inference_runtime(device) -> dict:
    """The manifest's record of an inference stage's machine (threads, device, CPU/GPU, torch)."""
    import torch

    return runtime_info(torch.get_num_threads(), device)


def autocast(device, precision: str):
    """bf16 autocast on `device` for precision 'bf16', else a no-op context."""
    import torch

    if precision != "bf16":
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16)
