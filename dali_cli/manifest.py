"""Stage execution contract: content hashes, manifest.json, up-to-date checks and atomic output.

A stage is a pure function of (input artifacts, parameters) → an output directory. `run_stage`
builds the output in `<out>.tmp-<pid>`, writes `manifest.json` last, and renames the directory into
place, so a crash never leaves a half-written artifact and never damages the previous one. A rerun
with the same inputs (by content hash), parameters and dali version is skipped.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import click

from dali_cli import __version__

MANIFEST_NAME = "manifest.json"
_HASH_BLOCK = 1 << 22


def hash_tree(path: str | Path, exclude: tuple[str, ...] = (MANIFEST_NAME,)) -> str:
    """blake2b over every file under `path` (relative names and bytes, sorted); a file works too."""
    path = Path(path)
    digest = hashlib.blake2b(digest_size=16)
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    for file in files:
        relative = file.name if file == path else file.relative_to(path).as_posix()
        if relative in exclude:
            continue
        digest.update(relative.encode())
        digest.update(b"\0")
        with open(file, "rb") as handle:
            while block := handle.read(_HASH_BLOCK):
                digest.update(block)
        digest.update(b"\1")
    return digest.hexdigest()


def content_hash(path: str | Path) -> str:
    """Hash of an input artifact: its manifest's recorded content hash, else a hash of its files."""
    path = Path(path)
    if not path.exists():
        raise click.ClickException(f"{path}: input not found")
    manifest = read_manifest(path) if path.is_dir() else None
    if manifest and isinstance(manifest.get("content_hash"), str):
        return manifest["content_hash"]
    return hash_tree(path)


def check_made_from(artifact: str | Path, role: str, expected_input: str | Path) -> None:
    """Refuse an artifact whose manifest says its `role` input was a different artifact.

    E.g. pseudo boxes made for one target frame set, passed with another target that happens to
    share frame ids. Artifacts without a manifest (imported or hand-made tables) pass unchecked.
    """
    artifact = Path(artifact)
    manifest = read_manifest(artifact) if artifact.is_dir() else None
    records = (manifest or {}).get("inputs", {}).get(role)
    if not records:
        return
    expected = content_hash(expected_input)
    if expected not in {record.get("hash") for record in records}:
        made_from = ", ".join(str(record.get("path")) for record in records)
        raise click.ClickException(
            f"{artifact}: made from {role} {made_from}, not from {expected_input} "
            f"(content hashes differ); pass the {role} it was made from"
        )


def read_manifest(directory: str | Path) -> dict | None:
    """The manifest of an artifact directory, or None when absent or unreadable."""
    path = Path(directory) / MANIFEST_NAME
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, NotADirectoryError, json.JSONDecodeError):
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


def why_stale(out: Path, stage: str, inputs: dict, params: dict) -> str | None:
    """Why `out` must be (re)built, or None when its manifest matches exactly."""
    manifest = read_manifest(out)
    if manifest is None:
        return "no output yet" if not out.exists() else "output has no valid manifest"
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


def _write_json_atomic(path: Path, document: dict) -> None:
    temporary = path.with_name(path.name + ".part")
    temporary.write_text(json.dumps(document, indent=2, sort_keys=False, default=str) + "\n")
    os.replace(temporary, path)


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def remove_stale_temporaries(out: Path) -> list[Path]:
    """Delete `<out>.tmp-<pid>` directories left by killed runs (their process is gone); a
    directory of a live process (a concurrent run) is left alone. Returns what was removed."""
    removed = []
    for path in out.parent.glob(f"{out.name}.tmp-*"):
        pid = path.name.rsplit("-", 1)[-1]
        if path.is_dir() and pid.isdigit() and not _process_alive(int(pid)):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


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
    echo: Callable[[str], None] = click.echo,
) -> StageOutcome:
    """Run `build(tmp_dir)` unless `out` is up to date, then move the result into place atomically.

    inputs: name → path (or list of paths) of input artifacts, hashed by content.
    params: JSON-serializable parameters; together with input hashes they decide staleness.
    build: writes the outputs into the given (empty) directory and returns counts/timings.
    """
    out = Path(out)
    params = _normalized(params)
    records = _input_records(inputs)
    reason = why_stale(out, stage, records, params)
    if reason is None and not force:
        echo(f"{stage}: {out} is up to date (use --force to rerun)")
        return StageOutcome("skipped", "up to date", read_manifest(out))
    reason = reason or "forced"
    if dry_run:
        echo(f"{stage}: would run -> {out} ({reason})")
        return StageOutcome("dry-run", reason)

    out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(out)
    temporary = out.parent / f"{out.name}.tmp-{os.getpid()}"
    if temporary.exists():
        shutil.rmtree(temporary)
    temporary.mkdir()
    started = time.perf_counter()
    try:
        result = build(temporary)
        if result is None:
            result = BuildResult()
        elif isinstance(result, dict):
            result = BuildResult(counts=result)
        wall = time.perf_counter() - started
        files = sorted(p for p in temporary.rglob("*") if p.is_file())
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
            "content_hash": hash_tree(temporary),
        }
        _write_json_atomic(temporary / MANIFEST_NAME, manifest)
        _replace_directory(temporary, out)
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)
        raise
    echo(f"{stage}: wrote {out} ({wall:.1f} s)")
    return StageOutcome("ran", reason, manifest)


def _replace_directory(new: Path, target: Path) -> None:
    """Move `new` to `target`, replacing an existing directory with only renames in between."""
    if not target.exists():
        os.rename(new, target)
        return
    retired = target.parent / f"{target.name}.old-{os.getpid()}"
    if retired.exists():
        shutil.rmtree(retired)
    os.rename(target, retired)
    try:
        os.rename(new, target)
    except BaseException:
        os.rename(retired, target)
        raise
    shutil.rmtree(retired, ignore_errors=True)
