"""Stage register: each scan's LiDAR pose by scan registration (dali_cli.registration), for
targets recorded without poses; writes the sequence table `dali track-pseudo --poses` reads."""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from dali_cli.registration import RegistrationError, RegistrationParams, register_scans
from dali_cli.runtime import console
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.store.artifacts import ChunkCache, FrameSet
from dali_cli.store.manifest import BuildResult, StageOutcome, run_stage
from dali_cli.store.sequence import (
    SEQUENCE_TABLE,
    read_sequence_if_any,
    registered_table,
    scan_order,
    write_table,
)

STAGE = "register"
SUMMARY_NAME = "summary.json"


def check_params(params: RegistrationParams) -> None:
    """ParameterError naming the field of a setting registration cannot run with."""
    for name, value in asdict(params).items():
        if not np.isfinite(value) or value < 0:
            raise ParameterError(name, f"must be finite and >= 0, got {value}")
    for name in ("voxel_m", "max_range_m", "max_correspondence_m", "kernel_m", "max_iterations"):
        if getattr(params, name) <= 0:
            raise ParameterError(name, f"must be > 0, got {getattr(params, name)}")
    if params.min_range_m >= params.max_range_m:
        raise ParameterError(
            ("min_range_m", "max_range_m"),
            f"the range {params.min_range_m:g}-{params.max_range_m:g} m is empty",
        )


def register(
    target_dir: str | Path,
    out: str | Path,
    *,
    params: RegistrationParams = RegistrationParams(),
    force: bool = False,
    dry_run: bool = False,
    progress: bool = True,
) -> StageOutcome:
    """Register the scans of `target_dir` recording by recording (each from its own first
    scan, in its index order) into `out`/sequence.parquet and summary.json; `progress`: a bar
    over the scans on stderr."""
    target_dir = Path(target_dir)
    check_params(params)

    def build(directory: Path) -> BuildResult:
        from dali_cli.merge import set_names

        frames = FrameSet(target_dir)
        frame_ids = list(frames.frame_ids)
        source = read_sequence_if_any(target_dir)
        index, recordings = scan_order(frame_ids, source, set_names(frames.attrs, frame_ids))
        groups = {}  # recording -> (scans,) positions in index order
        for name in dict.fromkeys(recordings):
            positions = np.array([i for i, r in enumerate(recordings) if r == name], np.int64)
            groups[name] = positions[np.argsort(index[positions], kind="stable")]
            if len(positions) < 2:
                what = f"recording '{name}'" if name else "the frame set"
                raise StageError(
                    f"{target_dir / 'frames.zarr'}: {what} has 1 scan "
                    f"('{frame_ids[positions[0]]}'): registration needs at least 2"
                )
        poses = np.tile(np.eye(4), (len(frame_ids), 1, 1))
        cache = ChunkCache(4)
        summary = {}
        bar = tqdm(total=len(frame_ids), desc="register", unit="scan", file=sys.stderr,
                   disable=not progress, leave=False)  # fmt: skip

        def scan_points(ids: list[str], k: int) -> np.ndarray:
            bar.update(1)
            return frames.frame(ids[k], cache)

        for name, positions in groups.items():
            ids = [frame_ids[p] for p in positions]
            label = f"recording '{name}'" if name else "the frame set"
            started = time.perf_counter()
            try:
                result = register_scans(len(ids), lambda k, ids=ids: scan_points(ids, k), params)
            except RegistrationError as error:
                bar.close()
                message = str(error).partition(": ")[2]
                raise StageError(
                    f"{target_dir / 'frames.zarr'}, frame '{ids[error.scan]}': {message}"
                ) from None
            poses[positions] = result.poses
            steps = np.linalg.norm(np.diff(result.poses[:, :3, 3], axis=0), axis=1)
            summary[name] = {
                "scans": len(ids),
                "path_length_m": round(float(steps.sum()), 3),
                "median_step_m": round(float(np.median(steps)), 4),
                "icp_iterations_median": float(np.median(result.iterations[1:])),
                "icp_iterations_max": int(result.iterations.max()),
                "not_converged": [ids[k] for k in np.flatnonzero(~result.converged)],
                "seconds": round(time.perf_counter() - started, 1),
            }
            console.echo(
                f"register: {label}: {len(ids)} scans, {steps.sum():.1f} m, "
                f"{len(summary[name]['not_converged'])} not converged"
            )
        bar.close()
        write_table(directory, registered_table(frame_ids, index, recordings, poses, source))
        (directory / SUMMARY_NAME).write_text(json.dumps({"recordings": summary}, indent=2) + "\n")
        counts = {
            "frames": len(frame_ids),
            "recordings": len(summary),
            "path_length_m": round(sum(r["path_length_m"] for r in summary.values()), 3),
            "not_converged": sum(len(r["not_converged"]) for r in summary.values()),
        }
        notes = [f"{SEQUENCE_TABLE}: LiDAR poses by scan registration (point-to-plane ICP)"]
        if source is None:
            notes.append("no sequence table in the target: scans ordered by frame id")
        return BuildResult(counts=counts, notes=notes)

    return run_stage(
        STAGE, out, inputs={"target": target_dir}, params=asdict(params), build=build,
        force=force, dry_run=dry_run,
    )  # fmt: skip
