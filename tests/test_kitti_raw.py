"""`dali import kitti-raw` on two real frames of KITTI raw drive 2011_09_26_drive_0001."""

from __future__ import annotations

import shutil
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from fixture_copies import writable_copy

from dali_cli.cli import main
from dali_cli.geometry import box_corners, count_points_in_boxes, point_box_indices, wrap_angle
from dali_cli.importers import kitti, kitti_raw
from dali_cli.importers.kitti_label import BBOX_COLUMNS
from dali_cli.store.artifacts import FrameSet, read_boxes

DAY = Path(__file__).resolve().parent / "fixtures" / "kitti_raw" / "2011_09_26"
DRIVE = DAY / "2011_09_26_drive_0001_sync"
FRAMES = ("0000000012", "0000000013")


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def imported(tmp_path: Path, *flags, drive: Path = DRIVE) -> Path:
    out = tmp_path / "out"
    result = invoke("import", "kitti-raw", drive, *flags, "--out", out)
    assert result.exit_code == 0, result.output
    return out


def xml_poses() -> list[tuple[int, str, list[float]]]:
    """(frame, type, [tx, ty, tz, rz, h, w, l]) of every pose, read straight from the XML."""
    poses = []
    for item in ElementTree.parse(DRIVE / "tracklet_labels.xml").getroot().iter("item"):
        if item.find("objectType") is None:
            continue
        size = [float(item.find(tag).text) for tag in ("h", "w", "l")]
        first = int(item.find("first_frame").text)
        for offset, pose in enumerate(item.find("poses").findall("item")):
            values = [float(pose.find(tag).text) for tag in ("tx", "ty", "tz", "rz")]
            poses.append((first + offset, item.find("objectType").text, values + size))
    return poses


def drive_calib() -> kitti.Calibration:
    return kitti_raw.read_raw_calib(DAY)[0]


def writable_day(tmp_path: Path) -> Path:
    return writable_copy(DAY, tmp_path / "2011_09_26")


def test_frames_and_box_counts_follow_the_xml(tmp_path):
    out = imported(tmp_path)
    frames = FrameSet(out)
    assert list(frames.frame_ids) == list(FRAMES)
    boxes = read_boxes(out)
    poses = xml_poses()
    assert any(frame == 14 for frame, _, _ in poses)  # a pose past the drive's last scan
    for frame_id in FRAMES:
        expected = sorted(kind for frame, kind, _ in poses if frame == int(frame_id))
        got = sorted(boxes.select(boxes.frame_id.astype(str) == frame_id)["label"].astype(str))
        assert got == expected
    assert len(boxes) == sum(frame in (12, 13) for frame, _, _ in poses)


def test_boxes_are_the_poses_with_the_centre_lifted_by_half_the_height(tmp_path):
    boxes = read_boxes(imported(tmp_path))
    for frame, _, (tx, ty, tz, rz, h, w, l) in xml_poses():  # noqa: E741
        if frame not in (12, 13):
            continue
        rows = boxes.boxes[boxes.frame_id.astype(str) == f"{frame:010d}"]
        distance = np.hypot(rows[:, 0] - tx, rows[:, 1] - ty)
        box = rows[int(np.argmin(distance))]
        np.testing.assert_allclose(box[:6], [tx, ty, tz + h / 2, l, w, h], atol=1e-6)
        assert abs(wrap_angle(box[6] - rz)) < 1e-6


def test_labelled_cars_hold_their_points(tmp_path):
    out = imported(tmp_path)
    frames, boxes = FrameSet(out), read_boxes(out)
    cars = boxes["label"].astype(str) == "Car"
    assert cars.sum() >= 10
    for frame_id in FRAMES:
        points = frames.frame(frame_id)
        rows = boxes.select((boxes.frame_id.astype(str) == frame_id) & cars)
        counts = count_points_in_boxes(points, rows.boxes)
        np.testing.assert_array_equal(rows["num_points"], counts)
        in_image = rows["truncated"] < 1
        assert (counts[in_image] >= 5).all(), counts
        # the box's floor sits on the car's lowest points (wheels on the road), within 30 cm
        owner = point_box_indices(points, rows.boxes)
        for index in np.flatnonzero(in_image & (counts >= 30)):
            floor = rows.boxes[index, 2] - rows.boxes[index, 5] / 2
            assert points[owner == index, 2].min() - floor < 0.3


def test_box_corners_project_onto_the_2d_box(tmp_path):
    boxes = read_boxes(imported(tmp_path))
    calib = drive_calib()
    projection = calib.P2 @ np.r_[calib.velo_to_rect[:3], [[0, 0, 0, 1]]]  # (3, 4) LiDAR -> px
    whole = boxes["truncated"] == 0
    assert whole.sum() >= 8
    corners = box_corners(boxes.boxes[whole])  # (N, 8, 3)
    pixels = np.c_[corners.reshape(-1, 3), np.ones(corners.size // 3)] @ projection.T
    uv = (pixels[:, :2] / pixels[:, 2:]).reshape(-1, 8, 2)
    expected = np.c_[uv.min(axis=1), uv.max(axis=1)]  # left, top, right, bottom
    got = np.stack([boxes[name][whole] for name in BBOX_COLUMNS], axis=1)
    np.testing.assert_allclose(got, expected, atol=0.5)


def test_heading_matches_the_kitti_label_convention(tmp_path):
    """rotation_y of the camera label = -rz - pi/2 (the object dataset's README formula)."""
    boxes = read_boxes(imported(tmp_path))
    _, _, rotation_y = kitti.lidar_boxes_to_camera(boxes.boxes, drive_calib())
    difference = wrap_angle(rotation_y - (-boxes.boxes[:, 6] - np.pi / 2))
    assert np.abs(difference).max() < 0.02


def test_occlusion_and_truncation_states(tmp_path):
    boxes = read_boxes(imported(tmp_path))
    assert set(np.unique(boxes["occluded"])) <= {0, 1, 2, 3}
    assert ((boxes["truncated"] >= 0) & (boxes["truncated"] <= 1)).all()
    states = kitti_raw.read_tracklets(DRIVE / "tracklet_labels.xml")
    kept = states.select(np.isin(states.frame, (12, 13)))
    assert sorted(boxes["occluded"]) == sorted(np.where(kept.occlusion < 0, 3, kept.occlusion))


def test_crop_fov_keeps_image_points_and_the_same_boxes(tmp_path):
    full = imported(tmp_path / "full")
    cropped = imported(tmp_path / "crop", "--crop-fov")
    calib, size = kitti_raw.read_raw_calib(DAY)
    for frame_id in FRAMES:
        every, kept = FrameSet(full).frame(frame_id), FrameSet(cropped).frame(frame_id)
        assert 0 < len(kept) < len(every)
        assert kitti.camera_fov_mask(kept, calib, size).all()
        assert kitti.camera_fov_mask(every, calib, size).sum() == len(kept)
    np.testing.assert_allclose(read_boxes(full).boxes, read_boxes(cropped).boxes)


def test_no_labels_and_calib_dir(tmp_path):
    out = imported(tmp_path / "a", "--no-labels")
    assert len(FrameSet(out).frame_ids) == 2
    assert not (out / "boxes.parquet").exists()
    drive = tmp_path / "elsewhere" / "drive"
    shutil.copytree(DRIVE, drive)
    result = invoke("import", "kitti-raw", drive, "--out", tmp_path / "b")
    assert result.exit_code == 1 and "calib_cam_to_cam.txt" in result.output
    out = imported(tmp_path / "c", "--calib-dir", DAY, drive=drive)
    assert len(read_boxes(out)) > 0


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda text: text.replace("<tx>", "<tx>x", 1), "tracklet 0, pose 0: field 'tx' is not"),
        (lambda text: text.replace("<rz>", "<rzz>", 1).replace("</rz>", "</rzz>", 1), "'rz'"),
        (lambda text: text[: len(text) // 2], "malformed XML"),
        (lambda text: text.replace("<h>", "<h>-", 1), "tracklet 0: size"),
        (
            lambda text: text.replace(
                "<!DOCTYPE boost_serialization>",
                '<!DOCTYPE boost_serialization [<!ENTITY a "aaaa">]>',
            ),
            "entities",
        ),
    ],
)
def test_malformed_tracklets_are_one_line_errors(tmp_path, edit, message):
    day = writable_day(tmp_path)
    path = day / DRIVE.name / "tracklet_labels.xml"
    path.write_text(edit(path.read_text()))
    out = tmp_path / "out"
    result = invoke("import", "kitti-raw", day / DRIVE.name, "--out", out)
    assert result.exit_code == 1
    assert message in result.output and "tracklet_labels.xml" in result.output
    assert not out.exists()


def test_malformed_calib_and_scans_are_errors(tmp_path):
    day = writable_day(tmp_path)
    cam = day / "calib_cam_to_cam.txt"
    cam.write_text(cam.read_text().replace("P_rect_02:", "P_rect_2:"))
    result = invoke("import", "kitti-raw", day / DRIVE.name, "--out", tmp_path / "a")
    assert result.exit_code == 1 and "'P_rect_02' missing" in result.output
    shutil.copy(DAY / "calib_cam_to_cam.txt", cam)
    velo = day / "calib_velo_to_cam.txt"
    velo.write_text(velo.read_text().replace("T:", "T: 1"))
    result = invoke("import", "kitti-raw", day / DRIVE.name, "--out", tmp_path / "b")
    assert result.exit_code == 1 and "'T' has 4 values" in result.output
    shutil.copy(DAY / "calib_velo_to_cam.txt", velo)
    scan = day / DRIVE.name / "velodyne_points" / "data" / f"{FRAMES[0]}.bin"
    scan.write_bytes(scan.read_bytes()[:-3])
    result = invoke("import", "kitti-raw", day / DRIVE.name, "--out", tmp_path / "c")
    assert result.exit_code == 1 and FRAMES[0] in result.output
    scan.rename(scan.with_name("scan.bin"))
    result = invoke("import", "kitti-raw", day / DRIVE.name, "--out", tmp_path / "d")
    assert result.exit_code == 1 and "not a frame index" in result.output
