"""What a stage's `--out` may be (docs/data-safety.md).

dali replaces its output as a whole, so an `--out` must be either a path that does not exist yet
or an artifact dali wrote before (a directory with a dali `manifest.json`). Anything else, a
user's directory, the current directory, a file, is refused rather than deleted. An output that
is, contains or lies inside one of the stage's inputs is refused too: replacing it would delete
or change the very data the stage reads.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

from dali_cli.runtime.errors import StageError

MANIFEST_NAME = "manifest.json"


class OutputPathError(StageError):
    """An `--out` dali must not write to; the message names it and says why."""


def is_dali_artifact(path: Path) -> bool:
    """A directory whose manifest.json was written by dali's stage runner."""
    try:
        manifest = json.loads((path / MANIFEST_NAME).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(manifest, dict) and "stage" in manifest and "dali_version" in manifest


def absolute(path: str | Path) -> Path:
    """`path` made absolute with symbolic links of its existing part resolved."""
    return Path(path).expanduser().resolve(strict=False)


def input_paths(inputs: Mapping[str, str | Path | list | tuple | None]) -> list[tuple[str, Path]]:
    """(role, absolute path) of every input, lists flattened."""
    pairs = []
    for role, value in inputs.items():
        if value is None:
            continue
        for item in value if isinstance(value, list | tuple) else [value]:
            if item is not None:
                pairs.append((role, absolute(item)))
    return pairs


def check_output_path(
    out: str | Path,
    inputs: Mapping[str, str | Path | list | tuple | None],
    *,
    directory: bool = True,
) -> Path:
    """Refuse an `--out` that dali must not write to; return it as an absolute path.

    directory: the output is an artifact directory (every stage but eval, which writes a file and
    checks an existing one itself). Raises OutputPathError naming `out` and the reason.
    """
    given = str(out)
    target = absolute(out)
    for ancestor in reversed(target.parents):
        if ancestor.exists() and not ancestor.is_dir():
            raise OutputPathError(
                f"--out {given}: {ancestor} is a file, not a directory: cannot write under it"
            )
    for role, path in input_paths(inputs):
        if target == path:
            raise OutputPathError(
                f"--out {given} is the {role} input: writing it would replace the data this "
                "stage reads; choose another --out"
            )
        if path.is_relative_to(target):
            raise OutputPathError(
                f"--out {given} contains the {role} input {path}: replacing it would delete "
                "that input; choose another --out"
            )
        if target.is_relative_to(path):
            raise OutputPathError(
                f"--out {given} lies inside the {role} input {path}: writing there would change "
                "that input; choose a path outside it"
            )
    if (
        directory
        and target.exists()
        and not (target.is_dir() and (is_dali_artifact(target) or is_unmanaged_eval_dir(target)))
    ):
        what = "a file" if not target.is_dir() else "a directory without a dali manifest.json"
        raise OutputPathError(
            f"--out {given} exists and is {what}. dali replaces its output as a whole, so it "
            "writes only to a new path or over an artifact it wrote itself; choose a new path, "
            "or move or delete it yourself"
        )
    return target


def is_dali_metrics_file(path: Path, marker: str = "sizes") -> bool:
    """A metrics file dali wrote: a JSON object with its `marker` block ("sizes": `dali eval`'s
    metrics.json, "bootstrap": `dali compare`'s)."""
    try:
        document = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(document, dict) and marker in document


def check_metrics_output(
    out: str | Path,
    inputs: Mapping[str, str | Path | list | tuple | None],
    marker: str = "sizes",
) -> Path:
    """`dali eval --out FILE` (`dali compare`: marker "bootstrap"): not an input nor inside one
    (`check_output_path`), and an existing file is replaced only when it is such a dali metrics
    file. Returns the absolute path."""
    target = check_output_path(out, inputs, directory=False)
    if target.is_dir():
        raise OutputPathError(f"--out {out} is a directory; give the metrics file to write")
    if target.exists() and not is_dali_metrics_file(target, marker):
        raise OutputPathError(
            f"--out {out} exists and is not a dali metrics file; choose a new path, or move or "
            "delete it yourself"
        )
    return target


# what `dali eval --out DIR/metrics.json` wrote into a directory before eval had a manifest
EVAL_FILES = ("metrics.json", "predictions.parquet", "metrics_kitti.json")


def is_unmanaged_eval_dir(path: Path) -> bool:
    """A directory holding only the files dali eval writes (its metrics.json a dali metrics
    file): an evaluation of an older run, which `dali eval --out DIR` may replace."""
    try:
        names = {p.name for p in path.iterdir()}
    except OSError:
        return False
    return (
        "metrics.json" in names
        and names <= set(EVAL_FILES)
        and all((path / name).is_file() for name in names)
        and is_dali_metrics_file(path / "metrics.json")
    )
