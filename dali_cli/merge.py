"""Several frame sets as one (e.g. a target of several drives): frame ids prefixed with their
set's name, `<name>-<frame id>`, so they stay unique and say where each frame came from.

Only sets of one sensor profile and one kind of point features merge: the fourth point value
means different things per source (KITTI's reflectance; nuScenes' intensity / 255; Waymo's
tanh of the intensity), and a detector trained on a mix would learn neither.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.store.frame_ids import name_problem
from dali_cli.store.manifest import BuildResult
from dali_cli.store.sequence import SEQUENCE_TABLE, merge_sequences, read_sequence, write_table

SEPARATOR = "-"
# importers whose fourth point value is the same quantity: the HDL-64E's reflectance in [0, 1]
KITTI_REFLECTANCE = ("kitti", "kitti-raw", "kitti-odometry")


@dataclass(frozen=True)
class MergeInput:
    """One set to merge: its name (the frame-id prefix) and its directory."""

    name: str
    directory: Path


def parse_inputs(specs: list[str] | tuple[str, ...]) -> list[MergeInput]:
    """`NAME=DIR` or `DIR` (named after its directory) per set; names must be unique and able
    to start a frame id (ParameterError naming the entry otherwise)."""
    inputs, seen = [], {}
    for position, spec in enumerate(specs):
        name, sep, directory = spec.partition("=")
        if not sep:
            name, directory = Path(spec).resolve().name, spec
        problem = name_problem(name)
        if problem is not None or SEPARATOR in name:
            why = problem or f"{name!r} contains '{SEPARATOR}', the separator of merged frame ids"
            raise ParameterError("specs", f"entry {position + 1} ('{spec}'): name {why}")
        if name in seen:
            raise ParameterError(
                "specs", f"entries {seen[name] + 1} and {position + 1} are both named '{name}'"
            )
        seen[name] = position
        inputs.append(MergeInput(name, Path(directory)))
    if not inputs:
        raise ParameterError("specs", "nothing to merge: give at least one --in")
    return inputs


def merged_id(name: str, frame_id: str) -> str:
    return f"{name}{SEPARATOR}{frame_id}"


def set_names(attrs: dict, frame_ids: list[str]) -> list[str]:
    """The set NAME of each `NAME-<id>` frame id of a merged frame set (`attrs`: its frames.zarr
    attributes, source_format 'merge'); '' for every frame of any other set (one recording)."""
    if attrs.get("source_format") != "merge":
        return [""] * len(frame_ids)
    return [frame_id.partition(SEPARATOR)[0] for frame_id in frame_ids]


def point_features(attrs: dict) -> str:
    """What a frame set's points hold, from its attrs: the KITTI importers' reflectance, else the
    set's source format (a merged set records the kind it merged)."""
    if "point_features" in attrs:
        return str(attrs["point_features"])
    source = str(attrs.get("source_format") or attrs.get("source") or "synthetic")
    return (
        "x, y, z, KITTI reflectance"
        if source in KITTI_REFLECTANCE
        else f"x, y, z, {source} intensity"
    )


def check_compatible(inputs: list[MergeInput], framesets: list) -> str:
    """The common point features; StageError naming the first set whose sensor profile or point
    features differ from the first set's."""
    first, first_set = inputs[0], framesets[0]
    features = point_features(first_set.attrs)
    for entry, frames in zip(inputs[1:], framesets[1:], strict=True):
        if frames.sensor != first_set.sensor:
            raise StageError(
                f"{entry.directory}: sensor profile '{frames.sensor}', but {first.directory} has "
                f"'{first_set.sensor}': only frame sets of one sensor merge"
            )
        other = point_features(frames.attrs)
        if other != features:
            raise StageError(
                f"{entry.directory}: points hold {other}, but {first.directory}'s hold "
                f"{features}: only frame sets with the same point features merge"
            )
    return features


def labelled(inputs: list[MergeInput], labels: bool) -> bool:
    """Whether the merged set gets boxes: every input has boxes.parquet and `labels`; a mix of
    labelled and unlabeled inputs is an error unless `labels` is False."""
    from dali_cli.store.artifacts import BOXES_NAME

    has = [(entry.directory / BOXES_NAME).is_file() for entry in inputs]
    if not labels or not any(has):
        return False
    if not all(has):
        with_boxes = inputs[has.index(True)].directory
        without = inputs[has.index(False)].directory
        raise StageError(
            f"{without}: no {BOXES_NAME}, but {with_boxes} has one: merge labelled sets or "
            "unlabeled ones (--no-labels drops every set's boxes)"
        )
    return True


def build_merge(
    out: str | Path, inputs: list[MergeInput], labels: bool, progress: bool = True
) -> BuildResult:
    """Write the merged FrameSet (and boxes.parquet, sequence.parquet when the inputs have them)
    into `out`, the stage's temporary directory."""
    from tqdm import tqdm

    from dali_cli.store.artifacts import BoxTable, FrameSet, FrameSetWriter, read_boxes, write_boxes

    framesets = [FrameSet(entry.directory) for entry in inputs]
    features = check_compatible(inputs, framesets)
    with_boxes = labelled(inputs, labels)
    drives = {
        entry.name: {
            "frames": len(frames),
            **{
                key: frames.attrs.get(key)
                for key in ("source_format", "crop_fov", "crop_front_deg")
            },
        }
        for entry, frames in zip(inputs, framesets, strict=True)
    }
    attrs = {"source_format": "merge", "point_features": features, "drives": drives}
    total = sum(len(frames) for frames in framesets)
    tables, sequences = [], []
    with FrameSetWriter(out, framesets[0].sensor, attrs) as writer:
        bar = tqdm(total=total, desc="merge", unit="frame", disable=not progress, leave=False)
        for entry, frames in zip(inputs, framesets, strict=True):
            for frame_id, points in frames.iter_frames():
                writer.append(merged_id(entry.name, frame_id), points)
                bar.update()
            if with_boxes:
                table = read_boxes(entry.directory)
                ids = np.array([merged_id(entry.name, f) for f in table.frame_id], dtype=object)
                tables.append(table.with_columns(frame_id=ids))
            if (entry.directory / SEQUENCE_TABLE).is_file():
                sequences.append((entry.name, read_sequence(entry.directory)))
        bar.close()
    counts = {
        "frames": writer.count,
        "points": int(writer.num_points),
        "frames_by_set": {name: drive["frames"] for name, drive in drives.items()},
    }
    notes = [f"frame ids: <set name>{SEPARATOR}<frame id>; points: {features}"]
    if tables:
        columns = [list(table.columns) for table in tables]
        if any(names != columns[0] for names in columns):
            odd = inputs[next(i for i, names in enumerate(columns) if names != columns[0])]
            raise StageError(
                f"{odd.directory}/boxes.parquet: columns {columns[inputs.index(odd)]} differ from "
                f"{inputs[0].directory}'s {columns[0]} (--no-labels merges the frames only)"
            )
        boxes = BoxTable.concat(tables)
        write_boxes(out, boxes)
        counts["boxes"] = len(boxes)
    if sequences:
        write_table(out, merge_sequences(sequences, merged_id))
        notes.append(
            f"{SEQUENCE_TABLE}: the per-frame times / poses of the sets that had them, "
            "recording = the set's name (each set's poses stay in its own world frame)"
        )
    return BuildResult(counts=counts, notes=notes)
