"""Stage execution contract: content hashes, manifest.json, up-to-date checks and atomic output.

A stage is a pure function of (input artifacts, parameters) → an output directory. `run_stage`
checks that `--out` may be written (`output_paths`), takes the output's lock, restores or cleans
what an interrupted run left (`atomic_dir`), builds the output in `<out>.tmp-<pid>-<token>`, writes
`manifest.json` last, and commits the directory in one atomic exchange, so a crash never leaves a
half-written artifact and never loses the previous one. A rerun with the same inputs (hashed from
their files, `file_hashes`), parameters and dali version, over an output whose files are intact,
is skipped. docs/data-safety.md says what this guarantees.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from dali_cli import __version__
from dali_cli.runtime import console
from dali_cli.runtime.errors import StageError, WriteError
from dali_cli.store.atomic_dir import (
    LEFTOVER_MARKER,
    OutputLock,
    make_temporary,
    recover_interrupted,
    remove_tree,
    replace_directory,
)
from dali_cli.store.atomic_file import write_text_atomically
from dali_cli.store.file_hashes import hash_tree as _hash_files
from dali_cli.store.foreign_files import foreign_files
from dali_cli.store.output_paths import OutputPathError, check_output_path
from dali_cli.store.regular_files import check_artifact_files

MANIFEST_NAME = "manifest.json"
# how content hashes are computed; manifests of older versions hashed raw bytes differently
HASH_METHOD = "blake2b-128 of names and per-file blake2b-128 digests"


def hash_tree(path: str | Path, exclude: tuple[str, ...] = (MANIFEST_NAME,)) -> str:
    """Content hash of an artifact directory (every file but its manifest and a leftover marker
    a crash may have left in it) or of one file."""
    return _hash_files(path, (*exclude, LEFTOVER_MARKER))


def content_hash(path: str | Path) -> str:
    """Hash of an input artifact, computed from its files (cached per file, see file_hashes);
    never the hash its own manifest claims, which a hand edit would leave unchanged."""
    path = Path(path)
    if not path.exists():
        raise StageError(f"{path}: input not found")
    check_artifact_files(path)
    return hash_tree(path)


def check_made_from(artifact: str | Path, role: str, expected_input: str | Path) -> None:
    """Refuse an artifact whose manifest says its `role` input was a different artifact.

    E.g. pseudo boxes made for one target frame set, passed with another target that happens to
    share frame ids. Artifacts without a manifest (imported or hand-made tables) pass unchecked.
    """
    artifact = Path(artifact)
    manifest = read_input_manifest(artifact) if artifact.is_dir() else None
    records = (manifest or {}).get("inputs", {}).get(role)
    if not records:
        return
    expected = content_hash(expected_input)
    if expected not in {record.get("hash") for record in records}:
        made_from = ", ".join(str(record.get("path")) for record in records)
        raise StageError(
            f"{artifact}: made from {role} {made_from}, not from {expected_input} "
            f"(content hashes differ); pass the {role} it was made from"
        )


def read_manifest(directory: str | Path) -> dict | None:
    """The manifest of an artifact directory, or None when absent or unreadable (not a file,
    not UTF-8, not JSON, not a JSON object): an output with such a manifest is rebuilt."""
    from dali_cli.store.regular_files import read_json_file

    path = Path(directory) / MANIFEST_NAME
    try:
        document = read_json_file(path, "manifest")
    except (StageError, OSError, ValueError):
        return None
    return document if isinstance(document, dict) else None


def read_input_manifest(directory: str | Path) -> dict | None:
    """The manifest of an input artifact: None when it has none; a StageError naming the file
    when it is there but unreadable (not a file, not UTF-8, not JSON, not a JSON object)."""
    path = Path(directory) / MANIFEST_NAME
    if not path.exists() and not path.is_symlink():
        return None
    from dali_cli.store.regular_files import read_json_file

    try:
        document = read_json_file(path, "manifest")
    except (StageError, OSError, ValueError) as error:
        reason = str(error).removeprefix(f"{path}: ")[:160]
        raise StageError(f"{path}: not a dali manifest ({reason})", path=path) from None
    problem = manifest_problem(document)
    if problem is not None:
        raise StageError(
            f"{path}: not a dali manifest ({problem}); the manifest is damaged (rebuild the "
            "artifact)",
            path=path,
        )
    return document


def manifest_problem(document) -> str | None:
    """What makes `document` no manifest dali could have written, None when nothing does: a
    JSON object whose `inputs` (when present) maps roles to lists of {path, hash} records of
    strings, and whose `outputs` (when present) holds a `files` count and a `counts` object."""
    if not isinstance(document, dict):
        return "not a JSON object"
    inputs = document.get("inputs", {})
    if not isinstance(inputs, dict):
        return "inputs is not an object"
    for role, records in inputs.items():
        if not isinstance(records, list):
            return f"inputs.{role} is not a list of input records"
        for index, record in enumerate(records):
            if not isinstance(record, dict) or not all(
                isinstance(record.get(key), str) for key in ("path", "hash")
            ):
                return f"inputs.{role}[{index}] is not a record of a path and a hash (strings)"
    outputs = document.get("outputs", {})
    if not isinstance(outputs, dict):
        return "outputs is not an object"
    files = outputs.get("files", 0)
    if isinstance(files, bool) or not isinstance(files, int) or files < 0:
        return "outputs.files is not a count of files"
    if not isinstance(outputs.get("counts", {}), dict):
        return "outputs.counts is not an object"
    return None


def _normalized(value):
    """JSON round trip so tuples/paths compare equal to what a manifest stores."""
    return json.loads(json.dumps(value, default=str, sort_keys=True))


@dataclass
class StageOutcome:
    """What `run_stage` did: 'ran', 'skipped' (up to date) or 'dry-run'."""

    status: str
    reason: str
    manifest: dict | None = None


@dataclass
class BuildResult:
    """What a stage's build function returns: counts and timings go into the manifest."""

    counts: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    extra: dict = field(default_factory=dict)


def _input_records(inputs: Mapping[str, str | Path | list]) -> dict:
    records = {}
    for name, value in inputs.items():
        if value is None:
            continue
        paths = value if isinstance(value, list | tuple) else [value]
        records[name] = [{"path": str(p), "hash": content_hash(p)} for p in paths]
    return records


def why_stale(
    out: Path, stage: str, inputs: dict, params: dict, derived: tuple[str, ...] = ()
) -> tuple[str | None, bool]:
    """Why `out` must be (re)built (None when its manifest matches exactly), and whether its
    files still match the manifest's content hash: then it holds no file its stage did not
    write, and a rebuild need not look for them (refuse_foreign_files hashes the tree again)."""
    manifest = read_manifest(out)
    if manifest is None:
        return ("no output yet" if not out.exists() else "output has no valid manifest"), False
    problem = manifest_problem(manifest)
    if problem is not None:
        return f"output's manifest is damaged ({problem})", False
    if manifest.get("hash_method") != HASH_METHOD:
        return (
            "output was written by an older dali (content hashes are computed differently)",
            False,
        )
    if manifest.get("content_hash") != hash_tree(out, (MANIFEST_NAME, *derived)):
        return "output files were changed since the stage wrote them", False
    return _why_changed(manifest, stage, inputs, params), True


def _why_changed(manifest: dict, stage: str, inputs: dict, params: dict) -> str | None:
    """Why an intact artifact (its files match its manifest) must be rebuilt, or None."""
    if manifest.get("stage") != stage:
        return f"output was written by stage '{manifest.get('stage')}'"
    if manifest.get("dali_version") != __version__:
        return f"dali version changed ({manifest.get('dali_version')} -> {__version__})"
    old_hashes = {k: [r["hash"] for r in v] for k, v in manifest.get("inputs", {}).items()}
    new_hashes = {k: [r["hash"] for r in v] for k, v in inputs.items()}
    if old_hashes != new_hashes:
        changed = sorted(
            k for k in set(old_hashes) | set(new_hashes) if old_hashes.get(k) != new_hashes.get(k)
        )
        return f"inputs changed: {', '.join(changed)}"
    if manifest.get("params") != params:
        old = manifest.get("params", {})
        changed = sorted(k for k in set(old) | set(params) if old.get(k) != params.get(k))
        return f"parameters changed: {', '.join(changed)}"
    return None


def refuse_foreign_files(given: Path, out: Path, stage: str, derived: tuple[str, ...]) -> None:
    """Before `out` is replaced: refuse (OutputPathError naming them) when it holds files its
    stage did not write, which the replacement would delete (foreign_files)."""
    manifest = read_manifest(out) if out.is_dir() else None
    if manifest is None:
        return  # nothing there, or (eval only) an older eval's files, checked by name
    foreign = foreign_files(out, manifest, (MANIFEST_NAME, LEFTOVER_MARKER, *derived), HASH_METHOD)
    if foreign:
        shown = ", ".join(foreign[:5]) + (
            f" and {len(foreign) - 5} more" if len(foreign) > 5 else ""
        )
        raise OutputPathError(
            f"{given}: {shown} inside it {'was' if len(foreign) == 1 else 'were'} not written by "
            f"{stage} (added or changed since); rerunning would delete "
            f"{'it' if len(foreign) == 1 else 'them'}, and dali never deletes a file it did not "
            f"write: move {'it' if len(foreign) == 1 else 'them'} out of {given}, then rerun"
        )


def _write_json_atomic(path: Path, document: dict) -> None:
    write_text_atomically(path, json.dumps(document, indent=2, sort_keys=False, default=str) + "\n")


def run_stage(
    stage: str,
    out: str | Path,
    inputs: Mapping[str, str | Path | list],
    params: dict,
    build: Callable[[Path], BuildResult | dict | None],
    *,
    force: bool = False,
    dry_run: bool = False,
    seed: int | None = None,
    echo: Callable[[str], None] = console.echo,
    derived: tuple[str, ...] = (),
) -> StageOutcome:
    """Run `build(tmp_dir)` unless `out` is up to date, then move the result into place atomically.

    inputs: name → path (or list of paths) of input artifacts, hashed by content.
    params: JSON-serializable parameters; together with input hashes they decide staleness.
    build: writes the outputs into the given (empty) directory and returns counts/timings.
    derived: names of files other commands may add to the artifact later (e.g. eval's
    metrics_kitti.json): not part of its content hash, gone when the stage rebuilds it.
    """
    given = Path(out)
    out = check_output_path(given, inputs, stage=stage)
    params = _normalized(params)
    if dry_run:
        reason, intact = why_stale(out, stage, _input_records(inputs), params, derived)
        if reason is None and not force:
            echo(f"{stage}: {given} is up to date (use --force to rerun)")
            return StageOutcome("skipped", "up to date", read_manifest(out))
        if not intact:
            refuse_foreign_files(given, out, stage, derived)
        echo(f"{stage}: would run -> {given} ({reason or 'forced'})")
        return StageOutcome("dry-run", reason or "forced")
    with OutputLock(out) as lock:
        recover_interrupted(out, echo, lock.inherited)
        records = _input_records(inputs)
        reason, intact = why_stale(out, stage, records, params, derived)
        if reason is None and not force:
            echo(f"{stage}: {given} is up to date (use --force to rerun)")
            return StageOutcome("skipped", "up to date", read_manifest(out))
        if not intact:
            refuse_foreign_files(given, out, stage, derived)
        reason = reason or "forced"
        manifest, wall = _build_and_commit(
            stage, out, records, params, build, seed, derived, lock.token
        )
    echo(f"{stage}: wrote {given} ({wall:.1f} s)")
    return StageOutcome("ran", reason, manifest)


def _build_and_commit(
    stage: str,
    out: Path,
    records: dict,
    params: dict,
    build: Callable,
    seed: int | None,
    derived: tuple[str, ...] = (),
    token: str | None = None,
) -> tuple[dict, float]:
    """Build into `<out>.tmp-<pid>-<token>`, write the manifest last, commit atomically; on
    any error (or Ctrl-C) remove the temporary directory and leave `out` as it was. A write
    error (a full disk included) is a WriteError naming `out`."""
    try:
        temporary = make_temporary(out, token)
    except OSError as error:
        raise WriteError(out, error) from None
    started = time.perf_counter()
    try:
        result = build(temporary)
        if result is None:
            result = BuildResult()
        elif isinstance(result, dict):
            result = BuildResult(counts=result)
        wall = time.perf_counter() - started
        files = sorted(p for p in temporary.rglob("*") if p.is_file() and p.name != LEFTOVER_MARKER)
        manifest = {
            "stage": stage,
            "dali_version": __version__,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "seed": seed,
            "params": params,
            "inputs": records,
            "outputs": {
                "files": len(files),
                "bytes": int(sum(p.stat().st_size for p in files)),
                "counts": _normalized(result.counts),
            },
            "timings": {"wall_seconds": round(wall, 3), **_normalized(result.timings)},
            "notes": list(result.notes),
            **_normalized(result.extra),
            "hash_method": HASH_METHOD,
            "content_hash": hash_tree(temporary, (MANIFEST_NAME, *derived)),
        }
        _write_json_atomic(temporary / MANIFEST_NAME, manifest)
        replace_directory(temporary, out, token=token)
    except OSError as error:
        remove_tree(temporary)
        raise WriteError(out, error) from None
    except BaseException:
        remove_tree(temporary)
        raise
    return manifest, wall
