"""FrameSet and box-table round trips, partial reads and validation errors."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import zarr

from dali_cli.store.artifacts import (
    ArtifactError,
    BoxTable,
    FrameSet,
    FrameSetWriter,
    TableValueError,
    int32_column,
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
    # zarr would fill the missing chunk with zeros: the reader refuses it, naming frame and chunk
    with pytest.raises(ArtifactError, match=r"chunk points/c/2/0 is missing; frame 'f2' lies"):
        frameset.frame(2)


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


def _swap_two_offsets(offsets):
    offsets[2], offsets[3] = offsets[3], offsets[2] - 1


def _grow_last_offset(offsets):
    offsets[-1] += 5


@pytest.mark.parametrize(
    "corrupt, message",
    [(_swap_two_offsets, "not monotone"), (_grow_last_offset, "last offset")],
    ids=["non-monotone", "not-matching-points"],
)
def test_bad_offsets_are_reported(tmp_path, corrupt, message):
    store = _make_frameset(tmp_path)
    group = zarr.open_group(str(store), mode="r+")
    offsets = group["offsets"][:]
    corrupt(offsets)
    group["offsets"][:] = offsets
    with pytest.raises(ArtifactError, match=message):
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


# ---------------------------------------------------------------------------------------------
# reads verify the chunks they read


def chunked_frames(tmp_path, compress=True):
    """Six 10-point frames in 10-point chunks: chunk k holds frame f{k}."""
    frames = [(f"f{i}", np.full((10, 4), i + 1, np.float32)) for i in range(6)]
    with FrameSetWriter(tmp_path, sensor="kitti", chunk_points=10, compress=compress) as writer:
        for frame_id, points in frames:
            writer.append(frame_id, points)
    return frames, tmp_path / "frames.zarr" / "points" / "c"


def _read_every_way(directory):
    frameset = FrameSet(directory)
    yield lambda: frameset.frame("f2")
    yield lambda: list(FrameSet(directory).iter_frames())
    yield lambda: FrameSet(directory).load_all()


def test_missing_chunk_is_an_error_naming_artifact_and_frame(tmp_path):
    frames, chunks = chunked_frames(tmp_path)
    (chunks / "2" / "0").unlink()
    for read in _read_every_way(tmp_path):
        with pytest.raises(
            ArtifactError, match=r"frames.zarr: points chunk points/c/2/0 is missing; frame 'f2'"
        ):
            read()
    # the frames in other chunks still read, and read right
    np.testing.assert_array_equal(FrameSet(tmp_path).frame("f3"), frames[3][1])


def test_missing_chunk_under_several_frames_names_them(tmp_path):
    frames = [(f"f{i}", np.full((4, 4), i + 1, np.float32)) for i in range(6)]
    write_frameset(tmp_path, frames, sensor="kitti", chunk_points=10)  # f2 spans chunks 0 and 1
    (tmp_path / "frames.zarr" / "points" / "c" / "1" / "0").unlink()
    with pytest.raises(ArtifactError, match=r"frames 'f2' to 'f4' \(3\) lie in it"):
        list(FrameSet(tmp_path).iter_frames())


@pytest.mark.parametrize("compress", [True, False])
def test_truncated_chunk_is_an_error_naming_artifact_and_frame(tmp_path, compress):
    _, chunks = chunked_frames(tmp_path, compress)
    path = chunks / "4" / "0"
    path.write_bytes(path.read_bytes()[:-7])
    for read in [lambda: FrameSet(tmp_path).frame("f4"), *list(_read_every_way(tmp_path))[1:]]:
        with pytest.raises(
            ArtifactError, match=r"chunk points/c/4/0 cannot be decoded .*frame 'f4'"
        ):
            read()


@pytest.mark.parametrize("compress", [True, False])
def test_flipped_bit_in_a_chunk_is_caught_by_its_checksum(tmp_path, compress):
    frames, chunks = chunked_frames(tmp_path, compress)
    path = chunks / "1" / "0"
    data = bytearray(path.read_bytes())
    data[len(data) // 3] ^= 0x10  # inside the payload (uncompressed: inside a float)
    path.write_bytes(bytes(data))
    with pytest.raises(ArtifactError, match=r"chunk points/c/1/0 cannot be decoded .*frame 'f1'"):
        list(FrameSet(tmp_path).iter_frames())
    np.testing.assert_array_equal(FrameSet(tmp_path).frame("f0"), frames[0][1])


# ---------------------------------------------------------------------------------------------
# empty tables keep their schema; int32 columns are range-checked


def ppcg_like(count: int) -> BoxTable:
    """A table with the extra columns a PPCG stage adds (strings and int32 counts)."""
    return BoxTable.from_arrays(
        [f"{i:03d}" for i in range(count)],
        np.ones((count, 7)),
        scale=np.ones(count),
        ppcg=np.array(["rc"] * count, dtype=object),
        model_id=np.array(["m"] * count, dtype=object),
        points_after=np.zeros(count, np.int32),
    )


def test_empty_table_has_the_schema_of_a_full_one(tmp_path):
    full, empty = tmp_path / "full", tmp_path / "empty"
    full.mkdir(), empty.mkdir()
    write_boxes(full, ppcg_like(3))
    write_boxes(empty, ppcg_like(3).select(np.zeros(3, bool)))
    assert pq.read_schema(empty / "boxes.parquet") == pq.read_schema(full / "boxes.parquet")
    loaded = read_boxes(empty)
    assert len(loaded) == 0 and loaded.extra_columns == [
        "scale",
        "ppcg",
        "model_id",
        "points_after",
    ]
    # and it can be written again, and concatenated with a full table
    write_boxes(empty, loaded)
    assert len(BoxTable.concat([loaded, read_boxes(full)])) == 3


def test_empty_null_typed_column_of_older_versions_reads_as_strings(tmp_path):
    table = ppcg_like(0).to_arrow()
    legacy = table.set_column(table.column_names.index("ppcg"), "ppcg", pa.array([]))  # null
    assert pa.types.is_null(legacy.schema.field("ppcg").type)
    pq.write_table(legacy, tmp_path / "boxes.parquet")
    loaded = read_boxes(tmp_path)
    assert len(loaded) == 0 and "ppcg" in loaded.columns
    write_boxes(tmp_path, loaded)
    assert pa.types.is_string(pq.read_schema(tmp_path / "boxes.parquet").field("ppcg").type)


@pytest.mark.parametrize("value", [2**40, -(2**31) - 1, 2**31, 1.5, np.nan, np.inf])
def test_num_points_out_of_int32_is_refused(tmp_path, value):
    counts = np.array([3, value, 5], dtype=np.float64 if isinstance(value, float) else np.int64)
    with pytest.raises(TableValueError, match=r"column 'num_points', row 1 \(frame 'b'\)"):
        BoxTable.from_arrays(["a", "b", "c"], np.ones((3, 7)), num_points=counts)
    table = BoxTable.from_arrays(["a", "b", "c"], np.ones((3, 7)))
    with pytest.raises(TableValueError, match=r"column 'num_points', row 1"):
        table.with_columns(num_points=counts)
    table.columns["num_points"] = counts  # behind the API's back: the writer still refuses
    with pytest.raises(TableValueError, match=r"column 'num_points', row 1"):
        write_boxes(tmp_path, table)
    assert not (tmp_path / "boxes.parquet").exists()


def test_num_points_out_of_int32_in_a_parquet_file_is_refused(tmp_path):
    arrow = sample_boxes().to_arrow()
    counts = pa.array([1, 2, 3, 2**40, 5], pa.int64())
    pq.write_table(arrow.set_column(arrow.column_names.index("num_points"), "num_points", counts),
                   tmp_path / "boxes.parquet")  # fmt: skip
    with pytest.raises(
        ArtifactError, match=r"boxes.parquet: column 'num_points', row 3 .*1099511627776"
    ):
        read_boxes(tmp_path)


def test_int32_column_keeps_what_fits():
    np.testing.assert_array_equal(
        int32_column(np.array([0, -(2**31), 2**31 - 1]), "n"), [0, -(2**31), 2**31 - 1]
    )
    np.testing.assert_array_equal(int32_column(np.array([2.0, -1.0]), "n"), [2, -1])
    assert int32_column(np.array([True, False]), "n").dtype == np.int32
    with pytest.raises(TableValueError, match="expected integers"):
        int32_column(np.array(["1"]), "n")


@pytest.mark.parametrize(
    ("column", "value", "problem"),
    [("score", np.nan, "NaN/inf score"), ("score", np.inf, "NaN/inf score"),
     ("w", -1.0, "negative size")],
)  # fmt: skip
def test_write_refuses_what_read_would_refuse(tmp_path, column, value, problem):
    table = sample_boxes()
    table.columns[column] = table.columns[column].copy()
    table.columns[column][2] = value
    with pytest.raises(TableValueError, match=f"row 2 \\(frame '.*'\\) has a {problem}"):
        write_boxes(tmp_path, table)
    assert not (tmp_path / "boxes.parquet").exists()
    pq.write_table(table.to_arrow(), tmp_path / "boxes.parquet")  # another tool wrote it
    with pytest.raises(ArtifactError, match=f"boxes.parquet: row 2 .*{problem}"):
        read_boxes(tmp_path)


def test_all_zero_offsets_are_stored_and_their_loss_is_detected(tmp_path):
    """Zarr skips chunks equal to the fill value by default: offsets of empty frames are all
    zeros, so the writer must store them anyway (a missing chunk is then damage, not zeros)."""
    write_frameset(tmp_path, [("a", np.zeros((0, 4))), ("b", np.zeros((0, 4)))], sensor="kitti")
    frameset = FrameSet(tmp_path)
    assert frameset.frame_ids == ["a", "b"] and frameset.num_points == 0
    store = tmp_path / "frames.zarr"
    shutil.rmtree(store / "offsets" / "c")
    with pytest.raises(ArtifactError, match=r"frames.zarr/offsets: 1 of 1 chunks missing"):
        FrameSet(tmp_path)
    # a frame set from before the writer stored every chunk (no marker) still reads its
    # legitimately absent all-zero offsets chunk as zeros
    group = zarr.open_group(str(store), mode="r+")
    del group.attrs["complete_chunks"]
    assert FrameSet(tmp_path).num_points == 0


@pytest.mark.parametrize("compress", [True, False])
@pytest.mark.parametrize("block_points", [16, 24, 40])
def test_streaming_reads_frames_that_straddle_blocks(tmp_path, monkeypatch, compress, block_points):
    """iter_frames reads block by block; frames across a block's end (or spanning several
    blocks, or empty at a boundary) come back exactly, in any order of indices."""
    import dali_cli.store.artifacts as artifacts

    rng = np.random.default_rng(block_points)
    sizes = [5, 11, 0, 30, 3, 17, 0, 9, 44, 1, 8, 13]
    frames = [(f"f{i}", rng.normal(size=(n, 4)).astype(np.float32)) for i, n in enumerate(sizes)]
    with artifacts.FrameSetWriter(tmp_path, "kitti", compress=compress, chunk_points=8) as writer:
        for frame_id, points in frames:
            writer.append(frame_id, points)
    monkeypatch.setattr(artifacts, "DEFAULT_CHUNK_POINTS", block_points)
    frameset = FrameSet(tmp_path)
    for indices in (None, [3, 8, 9, 0, 11, 5], list(range(len(frames)))[::-1]):
        expected = range(len(frames)) if indices is None else indices
        streamed = list(frameset.iter_frames(indices))
        assert [frame_id for frame_id, _ in streamed] == [frames[i][0] for i in expected]
        for (_, got), i in zip(streamed, expected, strict=True):
            np.testing.assert_array_equal(got, frames[i][1])
