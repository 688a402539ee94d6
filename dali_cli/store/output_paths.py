"""Which paths dali may write (docs/data-safety.md, "What dali writes"): the one rule every
command's output goes through.

dali writes only to a path it owns: a path that does not exist yet, or one it can prove it wrote
(an artifact with dali's manifest.json, a metrics file with dali's blocks, a PNG carrying dali's
Software tag, a report directory holding only dali's report files). It never writes an input,
inside an input, over or inside a user's file or directory, or inside an artifact of another
stage. Outputs that are one file (`check_file_output`) and outputs that are a directory
(`check_output_path`) are refused before any work starts, with a message that names the path
and says why.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

from dali_cli.runtime.errors import StageError

MANIFEST_NAME = "manifest.json"


class OutputPathError(StageError):
    """An `--out` dali must not write to; the message names it and says why."""


def read_json_quietly(path: Path):
    """The JSON document at `path`, or None when it is missing, not a file, not UTF-8 or not
    JSON (the callers decide ownership, which an unreadable file never proves)."""
    from dali_cli.runtime.errors import StageError
    from dali_cli.store.regular_files import read_json_file

    try:
        if path.is_symlink() or not path.is_file():
            return None
        return read_json_file(path)
    except (StageError, OSError, ValueError):
        return None


def is_dali_artifact(path: Path) -> bool:
    """A directory whose manifest.json was written by dali's stage runner."""
    manifest = read_json_quietly(path / MANIFEST_NAME)
    return isinstance(manifest, dict) and "stage" in manifest and "dali_version" in manifest


def artifact_stage(path: Path) -> str | None:
    """The stage that wrote the dali artifact `path` (its manifest's `stage`), else None."""
    manifest = read_json_quietly(path / MANIFEST_NAME)
    if not isinstance(manifest, dict) or "dali_version" not in manifest:
        return None
    stage = manifest.get("stage")
    return stage if isinstance(stage, str) else None


def artifact_around(path: Path) -> Path | None:
    """The dali artifact `path` is or lies inside (the nearest), None when there is none."""
    for candidate in (path, *path.parents):
        if candidate.is_dir() and is_dali_artifact(candidate):
            return candidate
    return None


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
    stage: str | None = None,
    option: str = "--out",
) -> Path:
    """Refuse an `--out` that dali must not write to; return it as an absolute path.

    directory: the output is an artifact directory (every stage but eval, which writes a file and
    checks an existing one itself). stage: the stage writing it; only `eval` may replace a
    directory holding just what an older `dali eval --out DIR/metrics.json` wrote. Raises
    OutputPathError naming `out` and the reason.
    """
    given = str(out)
    target = absolute(out)
    for ancestor in reversed(target.parents):
        if ancestor.exists() and not ancestor.is_dir():
            raise OutputPathError(
                f"{option} {given}: {ancestor} is a file, not a directory: cannot write under it"
            )
    for role, path in input_paths(inputs):
        if target == path:
            raise OutputPathError(
                f"{option} {given} is the {role} input: writing it would replace the data this "
                "stage reads; choose another --out"
            )
        if path.is_relative_to(target):
            raise OutputPathError(
                f"{option} {given} contains the {role} input {path}: replacing it would delete "
                "that input; choose another --out"
            )
        if target.is_relative_to(path):
            raise OutputPathError(
                f"{option} {given} lies inside the {role} input {path}: writing there would change "
                "that input; choose a path outside it"
            )
    if not directory:
        return target
    if target.exists() and not (
        target.is_dir()
        and not target.is_symlink()
        and (is_dali_artifact(target) or (stage == "eval" and is_unmanaged_eval_dir(target)))
    ):
        what = "a file" if not target.is_dir() else "a directory without a dali manifest.json"
        raise OutputPathError(
            f"{option} {given} exists and is {what}. dali replaces its output as a whole, so it "
            "writes only to a new path or over an artifact it wrote itself; choose a new path, "
            "or move or delete it yourself"
        )
    owner = artifact_stage(target) if target.is_dir() else None
    if stage is not None and owner is not None and owner != stage:
        raise OutputPathError(
            f"{option} {given} is an artifact of stage '{owner}': {stage} replaces only an "
            f"artifact {stage} wrote (--force included); choose another --out, or move or "
            "delete it yourself"
        )
    outer = artifact_around(target.parent)
    if outer is not None:
        raise OutputPathError(
            f"{option} {given} lies inside the dali artifact {outer} (of stage "
            f"'{artifact_stage(outer)}'): writing there would change it behind its manifest; "
            "choose a path outside it"
        )
    return target


def is_dali_metrics_file(path: Path, marker: str = "sizes") -> bool:
    """A metrics file dali wrote: a JSON object with its `marker` block ("sizes": `dali eval`'s
    metrics.json, with at least one AP block; "bootstrap": `dali compare`'s), each an object."""
    document = read_json_quietly(path)
    if not isinstance(document, dict) or not isinstance(document.get(marker), dict):
        return False
    if marker != "sizes":
        return True
    return any(isinstance(block, dict) and "bev" in block for block in document.values())


def check_metrics_output(
    out: str | Path,
    inputs: Mapping[str, str | Path | list | tuple | None],
    marker: str = "sizes",
    beside: tuple[str, ...] = (),
) -> Path:
    """`dali eval --out FILE` (`dali compare`: marker "bootstrap"): `check_file_output` with an
    existing file replaced only when it is such a dali metrics file. `beside`: names of files
    written next to it (eval's predictions.parquet), each checked the same way; such a file is
    dali's when FILE beside it is a dali metrics file (they were written together). Returns the
    absolute path of FILE."""
    target = check_file_output(
        out, inputs, lambda path: is_dali_metrics_file(path, marker), "a dali metrics file"
    )
    for name in beside:
        check_file_output(
            target.parent / name,
            inputs,
            lambda path: is_eval_predictions(path, target),
            f"a file dali eval wrote there with {target.name}",
            option=f"{name} beside --out",
        )
    return target


# the Parquet metadata key and value that mark a predictions file `dali eval` wrote
PREDICTIONS_MARK = (b"written_by", b"dali eval")


def is_eval_predictions(path: Path, metrics: Path) -> bool:
    """`path` is a predictions file `dali eval` wrote beside the metrics file `metrics`: it
    carries PREDICTIONS_MARK in its Parquet metadata, or (written by an older dali, unmarked)
    `metrics` is a dali metrics file of a model's evaluation and `path` was not written after
    it (they were written together, the predictions first). A user's predictions file, say the
    `--pred` of an earlier evaluation into that directory, is neither."""
    if path.is_symlink() or not path.is_file():
        return False
    try:
        import pyarrow.parquet as pq

        metadata = pq.read_schema(path).metadata or {}
    except Exception:  # not Parquet: not dali's
        return False
    document = read_json_quietly(metrics)
    if not is_dali_metrics_file(metrics) or not isinstance(document, dict):
        return False
    # the metrics file beside it must say that its evaluation wrote predictions (a model's, or
    # size-corrected ones): after `eval --pred DIR/predictions.parquet --out DIR/metrics.json`
    # the predictions are the user's, marked or not
    sources = [block.get("source") for block in document.values() if isinstance(block, dict)]
    from_model = any(isinstance(source, dict) and "model" in source for source in sources)
    if not (from_model or "size_correction" in document):
        return False
    if metadata.get(PREDICTIONS_MARK[0]) == PREDICTIONS_MARK[1]:
        return True
    return from_model and path.stat().st_ctime_ns <= metrics.stat().st_ctime_ns


# what `dali eval --out DIR/metrics.json` wrote into a directory before eval had a manifest
EVAL_FILES = ("metrics.json", "predictions.parquet", "metrics_kitti.json")


def is_unmanaged_eval_dir(path: Path) -> bool:
    """A directory holding only the files dali eval writes (its metrics.json a dali metrics
    file, and a predictions.parquet there one dali eval wrote with it, not a user's `--pred`):
    an evaluation of an older run, which `dali eval --out DIR` may replace."""
    try:
        names = {p.name for p in path.iterdir()}
    except OSError:
        return False
    return (
        "metrics.json" in names
        and names <= set(EVAL_FILES)
        and all((path / name).is_file() for name in names)
        and is_dali_metrics_file(path / "metrics.json")
        and all(
            is_eval_predictions(path / name, path / "metrics.json")
            for name in names
            if name.endswith(".parquet")
        )
    )


# files another command may add to an artifact of a stage, left out of its content hash (the
# Makefile's KITTI-protocol eval writes metrics_kitti.json into an eval artifact)
DERIVED_FILES: dict[str, tuple[str, ...]] = {"eval": ("metrics_kitti.json",)}


def is_derived_file(target: Path, artifact: Path) -> bool:
    """`target` is a file DERIVED_FILES allows directly inside the artifact `artifact`."""
    manifest = read_json_quietly(artifact / MANIFEST_NAME) or {}
    stage = manifest.get("stage")
    allowed = DERIVED_FILES.get(stage, ()) if isinstance(stage, str) else ()
    return target.parent == artifact and target.name in allowed


# the Software tag `dali view` writes into its PNGs (a tEXt chunk): how it knows a PNG is its own
PNG_SOFTWARE = "dali view"
REPORT_FILES = ("report.md", "report.json", "plots")
REPORT_MARKER = "written_by"


RECORDING_APPLICATION = "dali-recording"  # the application id of every recording dali writes


def file_head(path: Path, size: int) -> bytes:
    """The first `size` bytes of a regular file (b"" for anything else or an unreadable file);
    never opens anything but a regular file (a FIFO would block)."""
    if not Path(path).is_file():
        return b""
    try:
        with open(path, "rb") as file:
            return file.read(size)
    except OSError:
        return b""


def is_dali_recording(path: Path) -> bool:
    """A Rerun recording dali wrote (RRF2 magic, application id RECORDING_APPLICATION near the
    start)."""
    head = file_head(path, 1 << 12)
    return head.startswith(b"RRF2") and RECORDING_APPLICATION.encode() in head


def is_dali_png(path: Path) -> bool:
    """A PNG `dali view` wrote (its tEXt chunk Software = PNG_SOFTWARE)."""
    head = file_head(path, 1 << 16)
    return head.startswith(b"\x89PNG") and b"tEXtSoftware\x00" + PNG_SOFTWARE.encode() in head


def is_dali_report_dir(path: Path) -> bool:
    """A directory holding only what `dali report` writes, its report.json marked as dali's."""
    try:
        names = {p.name for p in path.iterdir()}
    except OSError:
        return False
    document = read_json_quietly(path / "report.json")
    if not names <= set(REPORT_FILES) or not isinstance(document, dict):
        return False
    # reports written before the marker: the report's own schema (a run or runs, and rows)
    older = "target" in document and ("run" in document or "runs" in document)
    return document.get(REPORT_MARKER) == "dali report" or older


def check_file_output(
    out: str | Path,
    inputs: Mapping[str, str | Path | list | tuple | None],
    owned: Callable[[Path], bool],
    what: str,
    option: str = "--out",
) -> Path:
    """A one-file output (a PNG, a metrics file, predictions beside one): not an input, inside
    one or containing one, not inside a dali artifact, and an existing file only when `owned`
    proves dali wrote it (`what` names such a file in the message). Returns the absolute path."""
    target = check_output_path(out, inputs, directory=False, option=option)
    linked = Path(out).is_symlink() or target.is_symlink()  # resolving follows a dangling link
    if linked or target.is_dir():
        kind = "a symbolic link" if linked else "a directory"
        raise OutputPathError(f"{option} {out} is {kind}; give the file to write")
    inside = artifact_around(target.parent)
    if inside is not None and not is_derived_file(target, inside):
        raise OutputPathError(
            f"{option} {out} lies inside the dali artifact {inside}: writing there would change "
            "it behind its manifest; choose a path outside it"
        )
    if target.exists() and not owned(target):
        raise OutputPathError(
            f"{option} {out} exists and is not {what}; choose a new path, or move "
            "or delete it yourself"
        )
    return target


def check_report_dir(out: str | Path) -> Path:
    """`dali report --out DIR`: a new directory, or one holding only an earlier dali report; not
    inside a dali artifact. Returns the absolute path."""
    target = check_output_path(out, {}, directory=False)
    inside = artifact_around(target)
    if inside is not None:
        raise OutputPathError(
            f"--out {out} lies inside the dali artifact {inside}: writing there would change it "
            "behind its manifest; choose a path outside it"
        )
    if target.exists() and not (target.is_dir() and is_dali_report_dir(target)):
        raise OutputPathError(
            f"--out {out} exists and is not a report directory dali wrote (only report.md, "
            "report.json and plots/); choose a new path, or move or delete it yourself"
        )
    return target
