"""A Rerun recording (`.rrd`) of a frame set to scrub through: the scans over time, boxes of any
number of tables (predictions coloured by score, true positive / false positive / missed against
labels where they exist, tracked cars with their ids) and the ego path where the frame set has
poses. `rerun-sdk` is an optional extra (`pip install rerun-sdk`; `make test` installs it).

Entities: `world/scan` (points), `world/<layer>` (boxes), `world/<layer>_missed` (labels no
prediction matched), `world/ego` (path so far). Timeline `frame`: the scan's position in the
frame set. Boxes are shown in each scan's LiDAR frame (`world` is the sensor at every frame),
unless the frame set has poses: then everything is in the first scan's frame.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.store.artifacts import BoxTable

TIMELINE = "frame"
MATCH_IOU = 0.5  # BEV IoU of a true positive where a layer is compared with labels
COLOURS = {"tp": (60, 200, 80), "fp": (230, 60, 60), "missed": (250, 200, 40),
           "labels": (80, 170, 250), "tracks": (200, 120, 250)}  # fmt: skip


@dataclass
class Layer:
    """A box table to show: its `name`, the table, and how to colour it ("score", "labels",
    "tracks": by the `car` column's id, "match": TP / FP against the truth layer)."""

    name: str
    table: BoxTable
    colour: str = "score"


def score_colours(scores: np.ndarray) -> np.ndarray:
    """`(n, 3)` uint8 colours from dark blue (score 0) to bright yellow (score 1)."""
    s = np.clip(np.asarray(scores, np.float64), 0.0, 1.0)[:, None]
    low, high = np.array([40, 40, 160]), np.array([255, 230, 40])
    return (low + s * (high - low)).astype(np.uint8)


def track_colours(ids: np.ndarray) -> np.ndarray:
    """`(n, 3)` uint8: a colour per id, the same for every box of one track."""
    rng = np.random.default_rng(np.asarray(ids, np.int64) % 100_003 + 7)
    return (
        rng.integers(60, 255, (len(ids), 3)).astype(np.uint8)
        if len(ids)
        else np.zeros((0, 3), np.uint8)
    )


def match_to_truth(pred: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pred_is_tp (P,), truth_found (T,)): greedy BEV IoU >= MATCH_IOU matching, predictions in
    the given (score) order."""
    from dali_cli.geometry import bev_iou

    found = np.zeros(len(truth), bool)
    tp = np.zeros(len(pred), bool)
    if len(pred) and len(truth):
        overlap = bev_iou(pred, truth)  # (P, T)
        for p in range(len(pred)):
            candidates = np.flatnonzero((overlap[p] >= MATCH_IOU) & ~found)
            if len(candidates):
                found[candidates[np.argmax(overlap[p, candidates])]] = True
                tp[p] = True
    return tp, found


def log_boxes(recording, path: str, boxes: np.ndarray, colours: np.ndarray, labels: list[str]):
    import rerun as rr

    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    recording.log(path, rr.Boxes3D(
        centers=boxes[:, :3], half_sizes=boxes[:, 3:6] / 2,
        rotation_axis_angles=[rr.RotationAxisAngle(axis=(0, 0, 1), radians=float(yaw))
                              for yaw in boxes[:, 6]],
        colors=colours, labels=labels,
    ))  # fmt: skip


def write_recording(path: Path, frames: Iterable[tuple[str, np.ndarray]], layers: list[Layer],
                    truth: BoxTable | None = None, poses: dict | None = None,
                    point_step: int = 1) -> dict:  # fmt: skip
    """Write the recording of `frames` ((frame id, (n, >=3) points) in order) with `layers` to
    `path` (.rrd); `truth`: labels the "match" layers are coloured against (and their misses
    shown); `poses`: frame id -> (4, 4) LiDAR pose, for the ego path and a common frame;
    `point_step`: log every k-th point. Returns the counts {frames, entities, boxes}. Written to
    a temporary file beside `path` and moved into place when complete."""
    import os
    import secrets

    import rerun as rr

    from dali_cli.store.output_paths import RECORDING_APPLICATION

    path = Path(path)
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(8)}")
    recording = rr.RecordingStream(RECORDING_APPLICATION)
    recording.save(str(temporary))
    try:
        counts = _log_frames(recording, frames, layers, truth, poses, point_step)
    except BaseException:
        recording.disconnect()
        temporary.unlink(missing_ok=True)
        raise
    recording.flush()
    recording.disconnect()
    os.replace(temporary, path)  # whole or not at all
    return counts


def _log_frames(recording, frames, layers, truth, poses, point_step) -> dict:
    """Log every frame of `frames` into `recording` (see write_recording); the counts."""
    import rerun as rr

    from dali_cli.labels.tracks import boxes_to_world

    rows = {layer.name: layer.table.rows_by_frame() for layer in layers}
    truth_rows = truth.rows_by_frame() if truth is not None else {}
    entities, count, boxes_logged, ego = {"world/scan"}, 0, 0, []
    for index, (frame_id, points) in enumerate(frames):
        recording.set_time(TIMELINE, sequence=index)
        pose = poses.get(frame_id) if poses else None
        xyz = np.asarray(points[::point_step, :3], np.float64)
        if pose is not None:
            xyz = xyz @ pose[:3, :3].T + pose[:3, 3]
            ego.append(pose[:3, 3])
            recording.log("world/ego", rr.LineStrips3D([np.asarray(ego)]))
            entities.add("world/ego")
        recording.log("world/scan", rr.Points3D(xyz, radii=0.03))
        for layer in layers:
            table = layer.table.select(rows[layer.name].get(frame_id, np.zeros(0, np.int64)))
            boxes = table.boxes if pose is None else boxes_to_world(table.boxes, pose)
            scores = np.asarray(table["score"]) if "score" in table.columns else np.ones(len(table))
            labels = [f"{s:.2f}" for s in scores]
            if layer.colour == "tracks" and "car" in table.columns:
                colours, labels = track_colours(table["car"]), [f"car {c}" for c in table["car"]]
            elif layer.colour == "labels":
                colours, labels = np.tile(COLOURS["labels"], (len(table), 1)), [""] * len(table)
            elif layer.colour == "match" and truth is not None:
                gt = truth.select(truth_rows.get(frame_id, np.zeros(0, np.int64)))
                order = np.argsort(-scores, kind="stable")
                tp_sorted, found = match_to_truth(table.boxes[order], gt.boxes)
                tp = np.zeros(len(table), bool)
                tp[order] = tp_sorted
                colours = np.where(tp[:, None], COLOURS["tp"], COLOURS["fp"]).astype(np.uint8)
                missed = gt.boxes[~found]
                missed = missed if pose is None else boxes_to_world(missed, pose)
                log_boxes(recording, f"world/{layer.name}_missed", missed,
                          np.tile(COLOURS["missed"], (len(missed), 1)), ["missed"] * len(missed))  # fmt: skip
                entities.add(f"world/{layer.name}_missed")
            else:
                colours = score_colours(scores)
            log_boxes(recording, f"world/{layer.name}", boxes, colours, labels)
            entities.add(f"world/{layer.name}")
            boxes_logged += len(table)
        count += 1
    return {"frames": count, "entities": len(entities), "boxes": boxes_logged}


def read_recording(path: Path) -> dict:
    """What a recording holds: {entity path: sorted frame indices it was logged at} (tests and
    `dali view`'s summary; rerun's RrdReader)."""
    from rerun.chunk import RrdReader

    seen: dict[str, set[int]] = {}
    for chunk in RrdReader(path).stream():
        entity = chunk.entity_path
        if not entity.startswith("/world"):
            continue
        batch = chunk.to_record_batch()
        frames = (
            set(batch.column(TIMELINE).to_pylist()) if TIMELINE in batch.schema.names else set()
        )
        seen.setdefault(entity, set()).update(int(f) for f in frames if f is not None)
    return {entity: sorted(frames) for entity, frames in seen.items()}


def record_frameset(out: Path, data_dir: Path, sources: list[tuple[str, Path]],
                    score_min: float | None = None, point_step: int = 1) -> dict:  # fmt: skip
    """The recording of every frame of the FrameSet `data_dir` with the box tables `sources`
    ((name, dir or .parquet)): a table with a `car` column shows its tracks, one named "labels"
    (the frame set's own) shows as labels and the others, when there are labels, as true
    positives, false positives and misses against them; the frame set's LiDAR poses, when it
    has them, give the ego path."""
    from dali_cli.labels.plausibility import refuse_implausible_table
    from dali_cli.store.artifacts import FrameSet, check_frames_known, read_boxes
    from dali_cli.store.sequence import SequenceError, read_lidar_poses

    frames = FrameSet(data_dir)
    layers, truth = [], None
    for name, path in sources:
        table = read_boxes(path)
        check_frames_known(table, frames.frame_ids, str(path))
        refuse_implausible_table(table, str(path))
        if score_min is not None and name != "labels" and "score" in table.columns:
            table = table.select(table["score"] >= score_min)
        if name == "labels":
            truth = table.select(np.char.lower(table["label"].astype(str)) == "car")
            layers.append(Layer(name, table, "labels"))
        else:
            layers.append(Layer(name, table, "tracks" if "car" in table.columns else "score"))
    if truth is not None:
        for layer in layers:
            if layer.colour == "score":
                layer.colour = "match"
    try:
        ids = list(frames.frame_ids)
        poses = dict(zip(ids, read_lidar_poses(data_dir, ids), strict=True))
    except SequenceError:
        poses = None
    return write_recording(out, frames.iter_frames(), layers, truth, poses, point_step)
