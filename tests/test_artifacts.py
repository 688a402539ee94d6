"""FrameSet and box-table round trips, partial reads and validation errors."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import zarr

from dali_cli.artifacts import (
    ArtifactError,
    BoxTable,
    FrameSet,
    FrameSetWriter,
    read_boxes,
    write_boxes,
    write_frameset,
)


def ragged_frames(seed: int = 0) -> list[tuple[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    sizes = [7, 0, 13, 1, 25, 0]
    return [(f"{i:06d}", rng.normal(size=(n, 4)).astype(np.float32)) for i, n in enumerate(sizes)]


def test_frameset_round_trip_with_empty_frames(tmp_path):
    frames = ragged_frames()
    write_frameset(tmp_path, frames, sensor="kitti", attrs={"origin": "test"}, chunk_points=8)
    frameset = FrameSet(tmp_path)
    assert frameset.frame_ids == [fid for fid, _ in frames]
    assert frameset.sensor == "kitti"
    assert frameset.attrs["frame_convention"] == "sensor"
    assert frameset.attrs["count"] == len(frames)
    assert frameset.attrs["origin"] == "test"
    for index, (fid, points) in enumerate(frames):
        np.testing.assert_array_equal(frameset.frame(index), points)
        np.testing.assert_array_equal(frameset.frame(fid), points)
    streamed = list(frameset.iter_frames())
    assert [fid for fid, _ in streamed] == [fid for fid, _ in frames]
    for (_, got), (_, want) in zip(streamed, frames, strict=True):
        np.testing.assert_array_equal(got, want)
    points, offsets = frameset.load_all()
    assert offsets.dtype == np.int64 and offsets[-1] == len(points) == sum(
        len(p) for _, p in frames
    )
    # a subset in any order reads the right frames
    picked = list(frameset.iter_frames([4, 0, 2]))
    assert [fid for fid, _ in picked] == ["000004", "000000", "000002"]
    np.testing.assert_array_equal(picked[0][1], frames[4][1])


def test_reading_one_frame_touches_only_its_chunks(tmp_path):
    frames = [(f"f{i}", np.full((10, 4), i + 1, np.float32)) for i in range(6)]
    write_frameset(tmp_path, frames, sensor="kitti", chunk_points=10)
    chunk_dir = tmp_path / "frames.zarr" / "points" / "c"
    chunk_files = sorted(p for p in chunk_dir.rglob("*") if p.is_file())
    assert len(chunk_files) == 6  # one chunk per frame with these sizes
    # delete every chunk except frame 3's: reading frame 3 must still work, frame 2 must not
    for path in chunk_files:
        if path.relative_to(chunk_dir).parts[0] != "3":
            path.unlink()
    frameset = FrameSet(tmp_path)
    np.testing.assert_array_equal(frameset.frame(3), frames[3][1])
    # zarr fills missing chunks with the fill value (0), so frame 2 comes back wrong, not as frame 2
    assert not np.array_equal(frameset.frame(2), frames[2][1])


def test_writer_rejects_bad_frames(tmp_path):
    writer = FrameSetWriter(tmp_path, sensor="kitti")
    with pytest.raises(ValueError, match="NaN"):
        writer.append("a", np.array([[0, 0, np.nan, 0]], np.float32))
    with pytest.raises(ValueError, match=r"\(n, 4\)"):
        writer.append("b", np.zeros((3, 3), np.float32))
    writer.append("c", np.zeros((1, 4)))
    with pytest.raises(ValueError, match="twice"):
        writer.append("c", np.zeros((1, 4)))


def _make_frameset(tmp_path):
    write_frameset(tmp_path, ragged_frames(), sensor="kitti", chunk_points=8)
    return tmp_path / "frames.zarr"


def test_missing_frameset_names_path(tmp_path):
    with pytest.raises(ArtifactError, match="frame set not found"):
        FrameSet(tmp_path / "nope")


def test_missing_array_is_reported(tmp_path):
    store = _make_frameset(tmp_path)
    shutil.rmtree(store / "offsets")
    with pytest.raises(ArtifactError, match="missing array 'offsets'"):
        FrameSet(tmp_path)


def test_non_monotone_offsets_are_reported(tmp_path):
    store = _make_frameset(tmp_path)
    group = zarr.open_group(str(store), mode="r+")
    offsets = group["offsets"][:]
    offsets[2], offsets[3] = offsets[3], offsets[2] - 1
    group["offsets"][:] = offsets
    with pytest.raises(ArtifactError, match="not monotone"):
        FrameSet(tmp_path)


def test_offsets_not_matching_points_are_reported(tmp_path):
    store = _make_frameset(tmp_path)
    group = zarr.open_group(str(store), mode="r+")
    offsets = group["offsets"][:]
    offsets[-1] += 5
    group["offsets"][:] = offsets
    with pytest.raises(ArtifactError, match="last offset"):
        FrameSet(tmp_path)


def test_wrong_points_dtype_is_reported(tmp_path):
    store = _make_frameset(tmp_path)
    group = zarr.open_group(str(store), mode="r+")
    del group["points"]
    group.create_array("points", data=np.zeros((46, 4), np.float64))
    with pytest.raises(ArtifactError, match="expected float32"):
        FrameSet(tmp_path)


def test_nan_points_are_reported_with_frame(tmp_path):
    store = _make_frameset(tmp_path)
    group = zarr.open_group(str(store), mode="r+")
    group["points"][22, 1] = np.inf  # frame '000002' spans points 7..20, '000003' is point 20
    frameset = FrameSet(tmp_path)
    with pytest.raises(ArtifactError, match="frame '000004'"):
        frameset.frame(4)
    with pytest.raises(ArtifactError, match="NaN/inf"):
        frameset.load_all()
    frameset.frame(0)  # other frames still read


def test_frame_id_count_mismatch_is_reported(tmp_path):
    store = _make_frameset(tmp_path)
    group = zarr.open_group(str(store), mode="r+")
    del group["frame_ids"]
    ids = group.create_array("frame_ids", shape=(2,), dtype=str)
    ids[:] = np.array(["a", "b"], dtype=object)
    with pytest.raises(ArtifactError, match="2 ids for 6 frames"):
        FrameSet(tmp_path)


# ---------------------------------------------------------------------------------------------
# box tables


def sample_boxes() -> BoxTable:
    rng = np.random.default_rng(1)
    boxes = np.column_stack(
        [rng.uniform(0, 50, (5, 3)), rng.uniform(1, 5, (5, 3)), rng.uniform(-3, 3, 5)]
    )
    return BoxTable.from_arrays(
        ["000000", "000002", "000000", "000004", "000002"],
        boxes,
        score=rng.uniform(size=5),
        num_points=np.arange(5),
        difficulty=np.array([0, 1, 2, 0, 1], np.int32),
        source=np.array(["a", "b", "c", "d", "e"], dtype=object),
    )


def test_box_table_round_trip(tmp_path):
    table = sample_boxes()
    write_boxes(tmp_path, table)
    loaded = read_boxes(tmp_path)
    assert list(loaded.columns) == list(table.columns)
    np.testing.assert_array_equal(loaded.boxes, table.boxes)
    np.testing.assert_array_equal(loaded["score"], table["score"])
    assert loaded["score"].dtype == np.float32 and loaded["num_points"].dtype == np.int32
    assert list(loaded.frame_id) == list(table.frame_id)
    assert list(loaded["source"]) == ["a", "b", "c", "d", "e"]
    assert loaded.extra_columns == ["difficulty", "source"]
    groups = loaded.rows_by_frame()
    assert {k: list(v) for k, v in groups.items()} == {
        "000000": [0, 2],
        "000002": [1, 4],
        "000004": [3],
    }
    assert len(loaded.for_frame("000002")) == 2
    assert len(BoxTable.concat([loaded, loaded])) == 10


def test_empty_box_table_round_trip(tmp_path):
    write_boxes(tmp_path, BoxTable.empty())
    loaded = read_boxes(tmp_path)
    assert len(loaded) == 0 and loaded.boxes.shape == (0, 7)
    assert loaded.rows_by_frame() == {}


def test_empty_box_table_with_string_columns_round_trip(tmp_path):
    # an empty ppcg-rc output (pseudo-labels found no car) must stay readable by retrain
    empty = BoxTable.empty().with_columns(ppcg=np.full(0, "raw", object), points_after=np.zeros(0))
    write_boxes(tmp_path, empty)
    loaded = read_boxes(tmp_path)
    assert len(loaded) == 0 and set(empty.columns) <= set(loaded.columns)
    assert loaded["ppcg"].astype(str).dtype.kind == "U"


def test_write_rejects_nan_boxes(tmp_path):
    table = sample_boxes()
    table.columns["x"][3] = np.nan
    with pytest.raises(ValueError, match="row 3"):
        write_boxes(tmp_path, table)
    assert not (tmp_path / "boxes.parquet").exists()


def _write_arrow(tmp_path, **overrides):
    table = sample_boxes().to_arrow()
    for name, array in overrides.items():
        index = table.column_names.index(name)
        table = table.set_column(index, name, array)
    pq.write_table(table, tmp_path / "boxes.parquet")


def test_read_reports_missing_column(tmp_path):
    pq.write_table(sample_boxes().to_arrow().drop(["yaw"]), tmp_path / "boxes.parquet")
    with pytest.raises(ArtifactError, match="missing column 'yaw'"):
        read_boxes(tmp_path)


def test_read_reports_wrong_column_type(tmp_path):
    _write_arrow(tmp_path, x=pa.array(["1", "2", "3", "4", "5"]))
    with pytest.raises(ArtifactError, match="column 'x' must be double"):
        read_boxes(tmp_path)


def test_read_reports_nested_column(tmp_path):
    table = sample_boxes().to_arrow().append_column("bad", pa.array([[1], [2], [3], [4], [5]]))
    pq.write_table(table, tmp_path / "boxes.parquet")
    with pytest.raises(ArtifactError, match="column 'bad' has unsupported type"):
        read_boxes(tmp_path)


def test_read_reports_nan_and_negative_sizes(tmp_path):
    _write_arrow(tmp_path, z=pa.array([0.0, 1.0, float("inf"), 0.0, 0.0]))
    with pytest.raises(ArtifactError, match=r"row 2 \(frame '000000'\) has NaN/inf"):
        read_boxes(tmp_path)
    _write_arrow(tmp_path, w=pa.array([1.0, -1.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ArtifactError, match="row 1 .* negative size"):
        read_boxes(tmp_path)


def test_read_reports_nulls_and_garbage(tmp_path):
    _write_arrow(tmp_path, frame_id=pa.array(["a", None, "b", "c", "d"]))
    with pytest.raises(ArtifactError, match="null"):
        read_boxes(tmp_path)
    (tmp_path / "boxes.parquet").write_text(json.dumps({"not": "parquet"}))
    with pytest.raises(ArtifactError, match="cannot read Parquet"):
        read_boxes(tmp_path)
    with pytest.raises(ArtifactError, match="box table not found"):
        read_boxes(tmp_path / "elsewhere")
