"""The PTSN scale contract: `<ptsn_dir>/scale.json`, written by `dali ptsn-sweep` and read by
pseudo-label, self-train and eval through `read_scale`, one reader with one set of rules.

`"scale"` is ŝ exactly as the search found it (JSON floats round-trip exactly), never rounded:
the pseudo labels are made at the very scale the sweep chose. The rest of the document (E_est,
E_pred at ŝ, the search record) is for people and `dali report` (docs/ptsn.md).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from dali_cli.artifacts import ArtifactError

SCALE_NAME = "scale.json"


def scale_path(scale_from: str | Path) -> Path:
    """`<dir>/scale.json` for a ptsn-sweep directory, or the file itself."""
    path = Path(scale_from)
    return path / SCALE_NAME if path.is_dir() else path


def read_scale(scale_from: str | Path) -> tuple[float, dict]:
    """(ŝ, the whole document) of a ptsn-sweep directory or its scale.json. ArtifactError naming
    the file when it is missing, not JSON, or its "scale" is not a finite positive number."""
    path = scale_path(scale_from)
    if not path.is_file():
        raise ArtifactError(f"{path}: scale file not found (is {scale_from} a ptsn-sweep output?)")
    try:
        document = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ArtifactError(f"{path}: invalid JSON ({error})") from None
    scale = document.get("scale") if isinstance(document, dict) else None
    if (
        isinstance(scale, bool)
        or not isinstance(scale, int | float)
        or not (math.isfinite(scale) and scale > 0)
    ):
        raise ArtifactError(f"{path}: field 'scale' must be a positive number, got {scale!r}")
    return float(scale), document


def write_scale(directory: str | Path, document: dict) -> Path:
    """Write `document` (with its exact "scale") as `<directory>/scale.json`."""
    scale = document.get("scale")
    if not (isinstance(scale, float | int) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale!r}")
    path = Path(directory) / SCALE_NAME
    path.write_text(json.dumps(document, indent=2) + "\n")
    return path
