"""The PTSN scale contract: `<ptsn_dir>/scale.json`, written by `dali ptsn-sweep` and read by
pseudo-label, self-train and eval through `read_scale`, one reader with one set of rules.

`"scale"` is ŝ exactly as the search found it (JSON floats round-trip exactly), never rounded:
the pseudo labels are made at the very scale the sweep chose. `read_scale` returns it typed as a
`ScaleResult` (ŝ, E_est, E_pred at ŝ, the pivot: the mount height scaled about, and the whole
record for people and `dali report`, docs/ptsn.md).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from dali_cli.store.artifacts import ArtifactError, read_json
from dali_cli.store.json_numbers import finite_number

SCALE_NAME = "scale.json"


def scale_path(scale_from: str | Path) -> Path:
    """`<dir>/scale.json` for a ptsn-sweep directory, or the file itself."""
    path = Path(scale_from)
    return path / SCALE_NAME if path.is_dir() else path


@dataclass(frozen=True)
class ScaleResult:
    """What a ptsn-sweep found: `scale` ŝ (exact), `e_est` and `e_pred` (l, w, h) in metres
    (E_pred at ŝ; None when not recorded), `pivot_m` the mount height the points were scaled
    about (None when not recorded) and `record`, the whole scale.json."""

    scale: float
    e_est: tuple[float, float, float] | None = None
    e_pred: tuple[float | None, ...] | None = None
    pivot_m: float | None = None
    record: dict = field(default_factory=dict)


def _measured(value) -> tuple | None:
    """(l, w, h) a sweep measured, an element None where it had no box to measure."""
    if not isinstance(value, list) or len(value) != 3:
        return None
    return tuple(finite_number(v) for v in value)


def read_scale(scale_from: str | Path) -> ScaleResult:
    """The ScaleResult of a ptsn-sweep directory or its scale.json. ArtifactError naming the file
    when it is missing, not JSON, or its "scale" is not a finite positive number."""
    path = scale_path(scale_from)
    document = read_json(
        path, f"scale file not found (is {scale_from} a ptsn-sweep output?)", "invalid JSON"
    )
    from dali_cli.quantities import CAR_SIZE_M, MOUNT_HEIGHT_M, SCALE, QuantityError, check_triple

    if not isinstance(document, dict):
        raise ArtifactError(f"{path}: not a scale file (not a JSON object)")
    try:  # the kinds of --scale and --target-size: a file is held to what an option is
        scale = SCALE.check(document.get("scale"), f"{path}: field 'scale'")
        e_est = document.get("E_est")
        if e_est is not None:
            e_est = check_triple(CAR_SIZE_M, e_est, f"{path}: field 'E_est'")
        pivot = document.get("mount_height_m")
        if pivot is not None:
            pivot = MOUNT_HEIGHT_M.check(pivot, f"{path}: field 'mount_height_m'")
    except QuantityError as error:
        raise ArtifactError(str(error)) from None
    return ScaleResult(
        scale=float(scale),
        e_est=e_est,
        e_pred=_measured(document.get("E_pred_at_scale")),
        pivot_m=pivot,
        record=document,
    )


def write_scale(directory: str | Path, document: dict) -> Path:
    """Write `document` (with its exact "scale") as `<directory>/scale.json`."""
    scale = document.get("scale")
    if not (isinstance(scale, float | int) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale!r}")
    path = Path(directory) / SCALE_NAME
    path.write_text(json.dumps(document, indent=2) + "\n")
    return path


def model_scale(model_dir: str | Path, scale: float | None, scale_from: str | Path | None) -> float:
    """The PTSN scale a model runs at: `scale`, else `scale_from`'s ŝ, else the model
    directory's own scale.json (a shipped adapted model's test-time scale), else 1.
    ParameterError when both `scale` and `scale_from` are given."""
    from dali_cli.runtime.errors import ParameterError

    if scale is not None and scale_from is not None:
        raise ParameterError(("scale", "scale_from"), "give one of the two, not both")
    if scale is not None:
        return float(scale)
    where = scale_from or (model_dir if (Path(model_dir) / SCALE_NAME).is_file() else None)
    return read_scale(where).scale if where is not None else 1.0
