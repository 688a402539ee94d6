"""Stage merge: several frame sets (e.g. imports of several drives) -> one FrameSet whose frame
ids say their set (dali_cli.merge)."""

from __future__ import annotations

from pathlib import Path

from dali_cli.store.manifest import StageOutcome, run_stage


def merge(
    specs: list[str] | tuple[str, ...],
    out: str | Path,
    *,
    labels: bool = True,
    force: bool = False,
    dry_run: bool = False,
    progress: bool = True,
) -> StageOutcome:
    """Merge the sets of `specs` (`NAME=DIR` or `DIR`) in order into `out`; their boxes too
    unless `labels` is False."""
    from dali_cli.merge import build_merge, parse_inputs

    inputs = parse_inputs(specs)
    params = {"names": [entry.name for entry in inputs], "labels": labels}
    records = {"inputs": [entry.directory for entry in inputs]}
    return run_stage(
        "merge", out, records, params,
        lambda tmp: build_merge(tmp, inputs, labels, progress=progress),
        force=force, dry_run=dry_run,
    )  # fmt: skip
