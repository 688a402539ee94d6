"""`dali merge`: one frame set from several, frame ids `<name>-<id>`, boxes and per-frame tables
carried, and sets of another sensor or other point features refused with nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.store.artifacts import BoxTable, FrameSet, FrameSetWriter, read_boxes, write_boxes


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def points_of(seed: int, count: int = 5) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 1, (count, 4)).astype(np.float32)


def frame_set(
    directory: Path,
    ids: list[str],
    seed: int,
    source_format: str = "kitti-raw",
    sensor: str = "kitti",
    boxes: bool = False,
) -> Path:
    """A small frame set: frame i of `ids` holds points_of(seed + i); with `boxes`, one box
    per frame at x = 10 + i."""
    with FrameSetWriter(directory, sensor, {"source_format": source_format}) as writer:
        for i, frame_id in enumerate(ids):
            writer.append(frame_id, points_of(seed + i))
    if boxes:
        rows = np.array([[10 + i, 0, 0, 4, 2, 1.5, 0] for i in range(len(ids))], np.float64)
        write_boxes(directory, BoxTable.from_arrays(ids, rows))
    return directory


@pytest.fixture
def drives(tmp_path) -> tuple[Path, Path]:
    one = frame_set(tmp_path / "2011_09_26_drive_0005", ["0000000000", "0000000001"], seed=0)
    two = frame_set(tmp_path / "seq04", ["000000", "000001", "000002"], 10, "kitti-odometry")
    return one, two


def assert_refused(result, out: Path, *words: str, exit_code: int = 1) -> None:
    assert result.exit_code == exit_code, result.output
    assert "Traceback" not in result.output
    last = result.output.strip().splitlines()[-1]
    for word in words:
        assert word in last, (word, last)
    assert not out.exists() and not list(out.parent.glob(f"{out.name}.tmp-*"))


def test_frames_keep_their_points_under_ids_that_name_their_set(drives, tmp_path):
    one, two = drives
    out = tmp_path / "target"
    result = invoke("merge", "--in", one, "--in", f"odometry_04={two}", "--out", out)
    assert result.exit_code == 0, result.output
    merged = FrameSet(out)
    assert merged.frame_ids == [
        "2011_09_26_drive_0005-0000000000",
        "2011_09_26_drive_0005-0000000001",
        "odometry_04-000000",
        "odometry_04-000001",
        "odometry_04-000002",
    ]
    for (source, seed), names in (((one, 0), 2), ((two, 10), 3)):
        for i in range(names):
            frame_id = FrameSet(source).frame_ids[i]
            prefix = "odometry_04" if source == two else source.name
            np.testing.assert_array_equal(merged.frame(f"{prefix}-{frame_id}"), points_of(seed + i))
    assert (
        merged.sensor == "kitti" and merged.attrs["point_features"] == "x, y, z, KITTI reflectance"
    )
    assert merged.attrs["drives"]["odometry_04"]["source_format"] == "kitti-odometry"
    assert not (out / "boxes.parquet").exists()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["outputs"]["counts"]["frames_by_set"] == {
        "2011_09_26_drive_0005": 2,
        "odometry_04": 3,
    }
    assert manifest["params"] == {"names": ["2011_09_26_drive_0005", "odometry_04"], "labels": True}
    again = invoke("merge", "--in", one, "--in", f"odometry_04={two}", "--out", out)
    assert again.exit_code == 0 and "up to date" in again.output


def test_boxes_and_sequence_tables_follow_their_frames(tmp_path):
    one = frame_set(tmp_path / "a", ["0", "1"], 0, boxes=True)
    two = frame_set(tmp_path / "b", ["0"], 5, "kitti", boxes=True)
    table = pa.table({"frame_id": ["0"], "index": [0], "time_s": [0.5]})
    pq.write_table(table, two / "sequence.parquet")
    out = tmp_path / "out"
    assert invoke("merge", "--in", one, "--in", two, "--out", out).exit_code == 0
    boxes = read_boxes(out)
    assert boxes.frame_id.tolist() == ["a-0", "a-1", "b-0"]
    np.testing.assert_array_equal(boxes["x"], [10, 11, 10])
    sequence = pq.read_table(out / "sequence.parquet").to_pydict()
    assert sequence["frame_id"] == ["b-0"] and sequence["time_s"] == [0.5]
    assert sequence["recording"] == ["b"]  # each set's poses in its own world frame
    unlabeled = tmp_path / "unlabeled"
    result = invoke("merge", "--in", one, "--in", two, "--no-labels", "--out", unlabeled)
    assert result.exit_code == 0 and not (unlabeled / "boxes.parquet").exists()


def test_a_mix_of_labelled_and_unlabeled_sets_is_refused(tmp_path):
    one = frame_set(tmp_path / "a", ["0"], 0, boxes=True)
    two = frame_set(tmp_path / "b", ["0"], 1)
    out = tmp_path / "out"
    result = invoke("merge", "--in", one, "--in", two, "--out", out)
    assert_refused(result, out, str(two), "no boxes.parquet", "--no-labels")


@pytest.mark.parametrize(
    ("kind", "words"),
    [
        ({"sensor": "waymo"}, ["sensor profile 'waymo'", "'kitti'"]),
        ({"source_format": "nuscenes"}, ["nuscenes intensity", "KITTI reflectance"]),
    ],
)
def test_another_sensor_or_other_point_features_are_refused(drives, tmp_path, kind, words):
    one, _ = drives
    other = frame_set(tmp_path / "other", ["0"], 3, **kind)
    out = tmp_path / "out"
    result = invoke("merge", "--in", one, "--in", other, "--out", out)
    assert_refused(result, out, str(other), *words)


@pytest.mark.parametrize(
    ("names", "words"),
    [
        (["x", "x"], ["--in", "entries 1 and 2", "'x'"]),
        (["a-b", "c"], ["--in", "entry 1", "separator"]),
        (["a/b", "c"], ["--in", "entry 1", "path separator"]),
    ],
)
def test_names_must_be_unique_frame_id_prefixes(drives, tmp_path, names, words):
    one, two = drives
    out = tmp_path / "out"
    result = invoke("merge", "--in", f"{names[0]}={one}", "--in", f"{names[1]}={two}", "--out", out)
    assert_refused(result, out, *words, exit_code=2)
