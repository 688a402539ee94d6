"""Stage track_pseudo: pseudo labels of a scan sequence kept only where they persist, one box per
parked car placed in every scan that holds it (dali_cli.labels.tracks); writes boxes.parquet in
pseudo-label's format (ppcg-rc, ppcg-cf and self-train read it unchanged), the pseudo labels'
scale.json and summary.json."""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict
from pathlib import Path

import numpy as np

from dali_cli.labels import tracks
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.store.artifacts import BoxTable, FrameSet, read_boxes, write_boxes
from dali_cli.store.manifest import BuildResult, StageOutcome, run_stage
from dali_cli.store.scale_file import scale_path
from dali_cli.store.sequence import SequenceError, read_lidar_poses, read_recordings

STAGE = "track_pseudo"
SUMMARY_NAME = "summary.json"


def recordings_of(target_dir: Path, attrs: dict, frame_ids: list[str]) -> list[str]:
    """The recording (drive) of each scan: the sequence table's `recording` column; for a
    merged set whose table predates it, the frame id's set name (`<name>-<id>`); else one."""
    from dali_cli.merge import set_names

    recordings = read_recordings(target_dir, frame_ids)
    return recordings if any(recordings) else set_names(attrs, frame_ids)


def track_pseudo(
    pseudo_dir: str | Path,
    target_dir: str | Path,
    out: str | Path,
    *,
    track_score_min: float = tracks.TRACK_SCORE_MIN,
    params: tracks.TrackParams = tracks.TrackParams(),
    poses_dir: str | Path | None = None,
    force: bool = False,
    dry_run: bool = False,
) -> StageOutcome:
    """Track the pseudo boxes of `pseudo_dir` (a `dali pseudo-label` output) over the scans of
    `target_dir` (its sequence table's poses and its points, never its labels), keep the tracked
    boxes scored >= `track_score_min` (a parked car: its boxes' median score; a moving track: its mean).
    `poses_dir`: read the poses and recordings from its sequence.parquet (`dali register`'s
    output) instead of the target's."""
    pseudo_dir, target_dir = Path(pseudo_dir), Path(target_dir)
    sequence_dir = Path(poses_dir) if poses_dir is not None else target_dir
    for name, value in asdict(params).items():
        if not np.isfinite(value) or value < 0 or (name == "gate_m" and value == 0):
            raise ParameterError(name, f"must be finite and > 0 (>= 0 for counts), got {value}")
    if not 0 <= track_score_min <= 1:
        raise ParameterError("track_score_min", f"must be in [0, 1], got {track_score_min}")
    stage_params = {"track_score_min": track_score_min, **asdict(params)}
    # the poses are an input (hashed) only when given: runs without them keep their manifests
    inputs = {"pseudo": pseudo_dir, "target": target_dir, "poses": poses_dir}

    def build(directory: Path) -> BuildResult:
        frames = FrameSet(target_dir)
        frame_ids = list(frames.frame_ids)
        try:
            poses = read_lidar_poses(sequence_dir, frame_ids)
            recordings = recordings_of(sequence_dir, frames.attrs, frame_ids)
        except SequenceError as error:
            how = (
                f"--poses must cover the scans of {target_dir}"
                if poses_dir is not None
                else "import the target with its poses, `dali import kitti-raw --poses`, or "
                "register its scans, `dali register`"
            )
            raise StageError(f"{error} ({how})") from None
        table = read_boxes(pseudo_dir)
        position = {frame_id: i for i, frame_id in enumerate(frame_ids)}
        unknown = sorted(set(table.frame_id) - set(position))
        if unknown:
            raise StageError(
                f"{pseudo_dir / 'boxes.parquet'}: frame '{unknown[0]}' is not a scan of "
                f"{target_dir} ({len(unknown)} such frames): pseudo labels of another target?"
            )
        frame = np.array([position[f] for f in table.frame_id], np.int64)
        tracked = tracks.track_boxes(
            frame, table.boxes, np.asarray(table["score"], np.float64),
            np.asarray(table["num_points"]), poses,
            lambda f: frames.frame(frame_ids[f]), params, recording=recordings,
        )  # fmt: skip
        keep = tracked.score >= track_score_min
        label = np.full(len(tracked.frame), "Car", dtype=object)
        moving = tracked.source_row >= 0
        label[moving] = np.asarray(table["label"], dtype=object)[tracked.source_row[moving]]
        out_table = BoxTable.from_arrays(
            np.asarray(frame_ids, dtype=object)[tracked.frame],
            tracked.boxes,
            score=tracked.score,
            label=label,
            num_points=tracked.num_points,
            track=tracked.car,
            parked=tracked.parked,
        ).select(keep)
        write_boxes(directory, out_table)
        source_scale = scale_path(pseudo_dir)
        if source_scale.is_file():  # ŝ of the pseudo labels, for self-train
            shutil.copyfile(source_scale, directory / source_scale.name)
        counts = {
            "frames": len(frame_ids),
            "recordings": len(set(recordings)),
            "input_boxes": len(table),
            "boxes": len(out_table),
            "parked_cars": int(len(np.unique(tracked.car[keep & tracked.parked]))),
            "moving_tracks": int(len(np.unique(tracked.car[keep & ~tracked.parked]))),
            "boxes_placed": int((keep & tracked.parked).sum()),
        }
        (directory / SUMMARY_NAME).write_text(json.dumps(counts, indent=2) + "\n")
        return BuildResult(counts=counts)

    return run_stage(
        STAGE, out, inputs=inputs, params=stage_params, build=build, force=force, dry_run=dry_run
    )
