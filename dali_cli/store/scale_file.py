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
from dali_cli.store.json_numbers import finite_number, finite_numbers

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


def _triple(value) -> tuple | None:
    """(l, w, h) from a JSON list of three positive finite numbers, else None (not recorded)."""
    return finite_numbers(value, 3, positive=True)


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
    given = document.get("scale") if isinstance(document, dict) else None
    scale = finite_number(given)
    if scale is None or scale <= 0:
        shown = repr(given) if len(repr(given)) < 40 else repr(given)[:40] + "..."
        raise ArtifactError(f"{path}: field 'scale' must be a positive number, got {shown}")
    pivot = finite_number(document.get("mount_height_m"))
    return ScaleResult(
        scale=float(scale),
        e_est=_triple(document.get("E_est")),
        e_pred=_measured(document.get("E_pred_at_scale")),
        pivot_m=pivot if pivot is not None and pivot >= 0 else None,
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
