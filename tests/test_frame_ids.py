"""Frame ids that could name a file outside an output directory are refused where data enters
(id lists, CSV columns, FrameSetWriter, FrameSet, box tables) and, independently, by every writer
that names a file after a frame (export kitti, export openpcdet, label_2 directories)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import zarr

from dali_cli.importers.common import ImportFormatError, read_id_list
from dali_cli.importers.nuscenes import read_boxes_csv
from dali_cli.store.artifacts import (
    ArtifactError,
    BoxTable,
    FrameSet,
    FrameSetWriter,
    TableValueError,
    read_boxes,
    write_boxes,
    write_frameset,
)
from dali_cli.store.frame_ids import (
    MAX_NAME_BYTES,
    FrameIdError,
    check_name,
    child_path,
    name_problem,
)

# (id, a fragment of the reason)
HOSTILE = [
    ("../../evil", "path separator"),
    ("/abs/x", "path separator"),
    ("a/b", "path separator"),
    ("a\\b", "path separator"),
    ("a\x00b", "control character"),
    ("tab\tid", "control character"),
    ("..", "directory reference"),
    (".", "directory reference"),
    ("x" * 300, "300 bytes long"),
    ("", "is empty"),
]
HOSTILE_IDS = [frame_id for frame_id, _ in HOSTILE]
# ids that reach the file system: each would escape a directory two levels below tmp_path
# ("ABS" stands for an absolute path under tmp_path, see `escaping`)
ESCAPING = ["../../evil", "..", "a/b", "ABS"]


def escaping(frame_id: str, tmp_path: Path) -> str:
    return str(tmp_path / "abs-evil") if frame_id == "ABS" else frame_id


def files_under(root: Path, skip: Path | None = None) -> set[str]:
    """Every file and directory under `root` (relative paths), except those under `skip`."""
    found = set()
    for path in root.rglob("*"):
        if skip is not None and (path == skip or skip in path.parents):
            continue
        found.add(str(path.relative_to(root)))
    return found


@pytest.mark.parametrize(
    "frame_id", ["000008", "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951",
                 "scene-0001_12", "фрейм-7", "a" * MAX_NAME_BYTES, ".hidden", "a..b"],
)  # fmt: skip
def test_ordinary_ids_are_accepted(frame_id):
    assert name_problem(frame_id) is None
    assert check_name(frame_id, "here") == frame_id


@pytest.mark.parametrize(("frame_id", "reason"), HOSTILE)
def test_hostile_ids_are_refused_with_a_reason(frame_id, reason):
    problem = name_problem(frame_id)
    assert problem is not None and reason in problem
    with pytest.raises(FrameIdError, match=r"^ids\.txt, line 4: frame id "):
        check_name(frame_id, "ids.txt, line 4")


def test_length_is_counted_in_utf8_bytes():
    assert name_problem("é" * (MAX_NAME_BYTES // 2)) is None  # 2 bytes each: exactly the limit
    assert "bytes long" in name_problem("é" * (MAX_NAME_BYTES // 2 + 1))
    assert "not a string" in name_problem(7)


@pytest.mark.parametrize("frame_id", HOSTILE_IDS)
def test_child_path_refuses_every_hostile_id(tmp_path, frame_id):
    with pytest.raises(FrameIdError):
        child_path(tmp_path, frame_id, ".txt")
    assert child_path(tmp_path, "000008", ".txt") == tmp_path / "000008.txt"


def test_child_path_refuses_a_symlink_that_leads_outside(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "f.txt").symlink_to(tmp_path / "elsewhere.txt")
    with pytest.raises(FrameIdError, match="outside"):
        child_path(tmp_path / "out", "f", ".txt")


# ---------------------------------------------------------------------------------------------
# where ids enter


@pytest.mark.parametrize(("frame_id", "reason"), HOSTILE)
def test_frameset_writer_refuses_hostile_ids(tmp_path, frame_id, reason):
    with FrameSetWriter(tmp_path, sensor="kitti") as writer:
        writer.append("ok", np.zeros((3, 4), np.float32))
        with pytest.raises(ValueError, match=f"frames.zarr, frame 1: frame id .*{reason}"):
            writer.append(frame_id, np.zeros((3, 4), np.float32))


@pytest.mark.parametrize(("frame_id", "reason"), HOSTILE)
def test_frameset_reader_refuses_hostile_ids(tmp_path, frame_id, reason):
    write_frameset(tmp_path, [("a", np.zeros((2, 4))), ("b", np.ones((2, 4)))], sensor="kitti")
    # a frame set written by another tool (or an older dali): overwrite the ids behind dali's back
    group = zarr.open_group(str(tmp_path / "frames.zarr"), mode="r+")
    group["frame_ids"][:] = np.asarray(["a", frame_id], dtype=object)
    with pytest.raises(ArtifactError, match=f"frames.zarr/frame_ids, frame 1: frame id .*{reason}"):
        FrameSet(tmp_path)


@pytest.mark.parametrize(("frame_id", "reason"), HOSTILE)
def test_write_boxes_refuses_hostile_ids_and_writes_nothing(tmp_path, frame_id, reason):
    table = BoxTable.from_arrays(["a", "a", frame_id], np.ones((3, 7)))
    with pytest.raises(TableValueError, match=f"row 2: frame id .*{reason}"):
        write_boxes(tmp_path, table)
    assert not (tmp_path / "boxes.parquet").exists()


@pytest.mark.parametrize(("frame_id", "reason"), HOSTILE)
def test_read_boxes_refuses_hostile_ids_in_a_prediction_file(tmp_path, frame_id, reason):
    table = BoxTable.from_arrays(["a", "b", frame_id, frame_id], np.ones((4, 7)))
    path = tmp_path / "predictions.parquet"
    pq.write_table(table.to_arrow(), path)  # as another tool would, without dali's checks
    with pytest.raises(ArtifactError, match=f"predictions.parquet: row 2: frame id .*{reason}"):
        read_boxes(path)


@pytest.mark.parametrize(("frame_id", "reason"), [h for h in HOSTILE if h[0].strip()])
def test_id_list_names_file_and_line(tmp_path, frame_id, reason):
    path = tmp_path / "ids.txt"
    path.write_text(f"000001\n# a comment\n\n{frame_id}\n000002\n")
    with pytest.raises(ImportFormatError, match=f"ids.txt, line 4: frame id .*{reason}"):
        read_id_list(path)


def test_id_list_duplicates_name_both_lines(tmp_path):
    path = tmp_path / "ids.txt"
    path.write_text("000001\n000002\n000001\n")
    with pytest.raises(ImportFormatError, match="line 3: duplicate frame id '000001'.*line 1"):
        read_id_list(path)


@pytest.mark.parametrize(("frame_id", "reason"), [h for h in HOSTILE if h[0]])
def test_nuscenes_csv_frame_id_column_names_the_line(tmp_path, frame_id, reason):
    path = tmp_path / "boxes.csv"
    with open(path, "w", newline="") as handle:
        handle.write("category,x,y,z,l,w,h,yaw,frame_id\n")
        handle.write("car,1,2,0,4,2,1.5,0,ok\n")
        handle.write(f"car,1,2,0,4,2,1.5,0,{frame_id}\n")
    with pytest.raises(ImportFormatError, match=f"line 3, column 'frame_id': frame id .*{reason}"):
        read_boxes_csv(path)


# ---------------------------------------------------------------------------------------------
# writers that name files after frames: the second, independent guard


def unchecked_table(frame_id: str) -> BoxTable:
    """A box table holding `frame_id` as it would be if an entry point forgot to check it."""
    return BoxTable.from_arrays(["000008", frame_id], np.tile([10.0, 0, -1, 4, 2, 1.5, 0], (2, 1)))


def _calib_dir(tmp_path: Path, frame_ids) -> Path:
    source = Path(__file__).parent / "fixtures" / "real" / "kitti" / "training" / "calib"
    calib = tmp_path / "calib"
    calib.mkdir()
    text = (source / "000008.txt").read_text()
    for frame_id in frame_ids:
        if name_problem(frame_id) is None:
            (calib / f"{frame_id}.txt").write_text(text)
    # a calib file where a hostile id's calib path would point: the write must still be refused
    (tmp_path / "evil.txt").write_text(text)
    return calib


@pytest.mark.parametrize("frame_id", ESCAPING)
def test_export_kitti_writes_nothing_outside_out(tmp_path, frame_id):
    from dali_cli.export import build_export_kitti

    frame_id = escaping(frame_id, tmp_path)
    calib = _calib_dir(tmp_path, ["000008"])
    out = tmp_path / "runs" / "export.tmp-1"
    out.mkdir(parents=True)
    before = files_under(tmp_path, skip=out)
    with pytest.raises(FrameIdError):
        build_export_kitti(out, unchecked_table(frame_id), ["000008", frame_id], calib)
    assert files_under(tmp_path, skip=out) == before


@pytest.mark.parametrize("frame_id", ESCAPING)
def test_export_openpcdet_writes_nothing_outside_out(tmp_path, frame_id):
    from dali_cli.importers.openpcdet import write_dataset

    frame_id = escaping(frame_id, tmp_path)
    out = tmp_path / "runs" / "export.tmp-1"
    out.mkdir(parents=True)
    before = files_under(tmp_path, skip=out)
    frames = [("000008", np.zeros((2, 4), np.float32)), (frame_id, np.zeros((2, 4), np.float32))]
    with pytest.raises(FrameIdError):
        write_dataset(out, frames, unchecked_table(frame_id))
    assert files_under(tmp_path, skip=out) == before


def test_export_openpcdet_refuses_a_split_name_outside_imagesets(tmp_path):
    from dali_cli.importers.openpcdet import write_dataset

    out = tmp_path / "runs" / "export.tmp-1"
    with pytest.raises(FrameIdError, match="ImageSets"):
        write_dataset(out, [("000008", np.zeros((2, 4), np.float32))], split="../../../evil")
    assert not out.exists()  # refused before the first file
    assert files_under(tmp_path) == set()


@pytest.mark.parametrize("frame_id", ESCAPING)
def test_label_dir_writer_writes_nothing_outside(tmp_path, frame_id):
    from dali_cli.importers.kitti_label import write_label_dir

    frame_id = escaping(frame_id, tmp_path)
    out = tmp_path / "runs" / "labels"
    with pytest.raises(FrameIdError):
        write_label_dir(out, unchecked_table(frame_id))
    assert files_under(tmp_path, skip=out) == {"runs"}


def test_absolute_id_would_land_outside_without_the_guard(tmp_path):
    """Why child_path exists: pathlib drops the directory for an absolute name."""
    target = tmp_path / "abs" / "x"
    assert (tmp_path / "out" / f"{target}.txt") == Path(f"{target}.txt")
    with pytest.raises(FrameIdError):
        child_path(tmp_path / "out", str(target), ".txt")
    assert not os.path.exists(f"{target}.txt")


def test_label_dir_reader_refuses_a_file_name_that_is_no_frame_id(tmp_path):
    from dali_cli.importers.kitti_label import read_label_dir

    line = "Car 0.00 0 -1.57 600 150 650 200 1.5 1.6 3.9 1.0 1.7 10.0 0.0\n"
    (tmp_path / "000001.txt").write_text(line)
    (tmp_path / "a\x01b.txt").write_text(line)
    with pytest.raises(FrameIdError, match=r"a\x01b.txt: file name: frame id .*control character"):
        read_label_dir(tmp_path)
