"""Importers on the real KITTI and nuScenes fixture frames, OpenPCDet round trips, bad input."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from fixture_copies import writable_copy
from hypothesis import given, settings
from hypothesis import strategies as st

from dali_cli.cli import main
from dali_cli.export import KITTI_COLUMNS
from dali_cli.geometry import box_corners, count_points_in_boxes
from dali_cli.importers import kitti, nuscenes
from dali_cli.store.artifacts import FrameSet, read_boxes
from dali_cli.store.manifest import read_manifest

DATA = Path(__file__).resolve().parent / "fixtures" / "real"
KITTI = DATA / "kitti"
KITTI_FRAME = KITTI / "training"
NUSCENES = DATA / "nuscenes"
NUSCENES_SCAN = NUSCENES / "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
NUSCENES_ID = NUSCENES_SCAN.name.removesuffix(".pcd.bin")

needs_fixtures = pytest.mark.skipif(
    not (KITTI_FRAME / "velodyne" / "000008.bin").is_file() or not NUSCENES_SCAN.is_file(),
    reason=f"real-data fixtures not found under {DATA} (tests/fixtures/real)",
)


def invoke(*args: str):
    return CliRunner().invoke(main, [str(a) for a in args])


def calib() -> kitti.Calibration:
    return kitti.read_calib(KITTI_FRAME / "calib" / "000008.txt")


def kitti_copy(tmp_path: Path) -> Path:
    """A writable copy of the KITTI fixture root."""
    return writable_copy(KITTI, tmp_path / "kitti")


def camera_frame_counts(
    points: np.ndarray, objects: kitti.CameraObjects, cal: kitti.Calibration
) -> np.ndarray:
    """Points inside each label box, counted in the rectified camera frame (no LiDAR boxes)."""
    rect = cal.lidar_to_rect(points)  # (n, 3)
    counts = []
    for location, (h, w, length), ry in zip(
        objects.location, objects.hwl, objects.rotation_y, strict=True
    ):
        d = rect - location
        along = np.cos(ry) * d[:, 0] - np.sin(ry) * d[:, 2]
        across = np.sin(ry) * d[:, 0] + np.cos(ry) * d[:, 2]
        inside = (
            (np.abs(along) <= length / 2)
            & (np.abs(across) <= w / 2)
            & (d[:, 1] <= 0)
            & (d[:, 1] >= -h)
        )
        counts.append(int(inside.sum()))
    return np.asarray(counts)


# ---------------------------------------------------------------------------------------------
# KITTI


@needs_fixtures
def test_kitti_import_fixture(tmp_path):
    out = tmp_path / "kitti_set"
    result = invoke("import", "kitti", KITTI, "--out", out)
    assert result.exit_code == 0, result.output
    frames = FrameSet(out)
    assert frames.frame_ids == ["000008"] and frames.sensor == "kitti"
    points = frames.frame("000008")
    raw = np.fromfile(KITTI_FRAME / "velodyne" / "000008.bin", np.float32).reshape(-1, 4)
    np.testing.assert_array_equal(points, raw)

    table = read_boxes(out)
    labels = table["label"].astype(str)
    assert (labels == "Car").sum() == 6 and (labels == "DontCare").sum() == 4
    for column in KITTI_COLUMNS:  # the label fields dali keeps (and export writes back)
        assert column in table.columns
    cars = table.select(labels == "Car")
    # the stored counts are the frame's points inside the stored boxes ...
    np.testing.assert_array_equal(cars["num_points"], count_points_in_boxes(points, cars.boxes))
    # ... and agree with counting inside the original camera-frame boxes (only the camera tilt differs)
    objects = kitti.parse_label_file(KITTI_FRAME / "label_2" / "000008.txt")
    reference = camera_frame_counts(points, objects, calib())[:6]
    assert np.all(np.abs(cars["num_points"] - reference) <= np.maximum(3, 0.05 * reference)), (
        cars["num_points"],
        reference,
    )
    assert cars["num_points"].min() > 20
    assert np.all(table.select(labels == "DontCare")["num_points"] == 0)
    manifest = read_manifest(out)
    assert manifest["outputs"]["counts"]["boxes_by_label"] == {"Car": 6, "DontCare": 4}


@needs_fixtures
def test_kitti_boxes_match_readme_formula():
    """Centre and yaw against the plain formula of the fixture's README (yaw = -ry - pi/2)."""
    objects = kitti.parse_label_file(KITTI_FRAME / "label_2" / "000008.txt")
    cars = objects.type == "Car"
    cal = calib()
    boxes = kitti.camera_boxes_to_lidar(objects.location, objects.hwl, objects.rotation_y, cal)[
        cars
    ]
    centre_cam = objects.location[cars] - np.c_[np.zeros(6), objects.hwl[cars, 0] / 2, np.zeros(6)]
    homogeneous = np.c_[centre_cam, np.ones(6)] @ np.linalg.inv(cal.velo_to_rect).T
    np.testing.assert_allclose(boxes[:, :3], homogeneous[:, :3], atol=1e-9)
    np.testing.assert_allclose(boxes[:, 3:6], objects.hwl[cars][:, ::-1])
    yaw_error = np.angle(np.exp(1j * (boxes[:, 6] - (-objects.rotation_y[cars] - np.pi / 2))))
    assert np.abs(yaw_error).max() < 0.01
    assert np.all(boxes[:, 0] > 0)  # all in front of the car


@needs_fixtures
@settings(max_examples=40, deadline=None)
@given(
    xy=st.tuples(st.floats(-60, 60), st.floats(-60, 60)),
    z=st.floats(-3, 1),
    lwh=st.tuples(st.floats(0.5, 12), st.floats(0.3, 3), st.floats(0.3, 4)),
    yaw=st.floats(-np.pi, np.pi - 1e-9),
)
def test_camera_lidar_conversion_round_trip(xy, z, lwh, yaw):
    cal = calib()
    box = np.array([[*xy, z, *lwh, yaw]])
    location, hwl, rotation_y = kitti.lidar_boxes_to_camera(box, cal)
    back = kitti.camera_boxes_to_lidar(location, hwl, rotation_y, cal)
    np.testing.assert_allclose(back[:, :6], box[:, :6], atol=1e-9)
    assert abs(np.angle(np.exp(1j * (back[0, 6] - yaw)))) < 1e-3
    assert -np.pi <= rotation_y[0] < np.pi and -np.pi <= back[0, 6] < np.pi
    # the camera box's corners are the LiDAR box's corners, up to the camera tilt (about 0.018 rad)
    camera_corners = kitti.camera_box_corners(location, hwl, rotation_y)[0]  # (8, 3)
    lidar_corners = cal.lidar_to_rect(box_corners(box)[0])  # (8, 3)
    distances = np.linalg.norm(camera_corners[:, None] - lidar_corners[None], axis=2)
    assert distances.min(axis=1).max() < 0.02 * np.linalg.norm(lwh) / 2 + 1e-6


@needs_fixtures
def test_calib_parse_and_transforms():
    cal = calib()
    assert (
        cal.P2.shape == (3, 4)
        and cal.R0_rect.shape == (3, 3)
        and cal.Tr_velo_to_cam.shape == (3, 4)
    )
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-50, 50, (100, 3))
    np.testing.assert_allclose(cal.rect_to_lidar(cal.lidar_to_rect(xyz)), xyz, atol=1e-9)
    # LiDAR +x (forward) is camera +z, LiDAR +y (left) is camera -x, LiDAR +z (up) is camera -y
    axes = cal.lidar_to_rect(np.eye(3)) - cal.lidar_to_rect(np.zeros((1, 3)))
    np.testing.assert_allclose(axes, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=0.02)


@needs_fixtures
def test_kitti_frames_without_labels(tmp_path):
    root = tmp_path / "kitti"
    (root / "testing" / "velodyne").mkdir(parents=True)
    shutil.copy(
        KITTI_FRAME / "velodyne" / "000008.bin", root / "testing" / "velodyne" / "000008.bin"
    )
    out = tmp_path / "unlabeled"
    result = invoke("import", "kitti", root, "--split", "testing", "--out", out)
    assert result.exit_code == 0, result.output
    assert len(FrameSet(out)) == 1 and not (out / "boxes.parquet").exists()
    assert read_manifest(out)["outputs"]["counts"]["frames_without_labels"] == 1


@needs_fixtures
def test_kitti_crop_fov_keeps_only_image_points(tmp_path):
    out = tmp_path / "fov"
    assert invoke("import", "kitti", KITTI, "--crop-fov", "--out", out).exit_code == 0
    points = FrameSet(out).frame(0)
    pixels, depth = calib().rect_to_image(calib().lidar_to_rect(points))
    assert 0 < len(points) <= 17238
    assert (depth > 0).all() and (pixels[:, 0] >= 0).all() and (pixels[:, 0] < 1242).all()


def _expect_error(result, out: Path, *fragments: str) -> None:
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    for fragment in fragments:
        assert fragment in result.output, (fragment, result.output)
    assert not out.exists()
    assert not list(out.parent.glob(f"{out.name}.tmp-*"))


def _truncate_scan(root: Path) -> None:
    scan = root / "training" / "velodyne" / "000008.bin"
    scan.write_bytes(scan.read_bytes()[:-6])


def _nan_point(root: Path) -> None:
    scan = root / "training" / "velodyne" / "000008.bin"
    points = np.fromfile(scan, np.float32).reshape(-1, 4)
    points[1234, 1] = np.nan
    points.tofile(scan)


def _remove_calib(root: Path) -> None:
    (root / "training" / "calib" / "000008.txt").unlink()


def _label_with_14_fields(root: Path) -> None:
    label = root / "training" / "label_2" / "000008.txt"
    lines = label.read_text().splitlines()
    lines[2] = " ".join(lines[2].split()[:14])
    label.write_text("\n".join(lines) + "\n")


def _bad_label_value(root: Path) -> None:
    label = root / "training" / "label_2" / "000008.txt"
    label.write_text(label.read_text().replace("3.23 -2.70", "3.23 abc", 1))


def _calib_without_r0_rect(root: Path) -> None:
    calib_path = root / "training" / "calib" / "000008.txt"
    text = calib_path.read_text().splitlines()
    calib_path.write_text("\n".join(line for line in text if not line.startswith("R0_rect")))


@needs_fixtures
@pytest.mark.parametrize(
    "damage, fragments",
    [
        (_truncate_scan, ("000008.bin", "not a multiple of 16")),
        (_nan_point, ("000008.bin", "point 1234", "NaN")),
        (_remove_calib, ("calib", "000008")),
        (_label_with_14_fields, ("000008.txt:3", "got 14")),
        (_bad_label_value, ("000008.txt:1", "'abc'")),
        (_calib_without_r0_rect, ("R0_rect", "missing")),
    ],
)
def test_a_damaged_kitti_file_is_an_error(tmp_path, damage, fragments):
    root = kitti_copy(tmp_path)
    damage(root)
    out = tmp_path / "out"
    _expect_error(invoke("import", "kitti", root, "--out", out), out, *fragments)


@needs_fixtures
def test_failed_reimport_keeps_previous_output(tmp_path):
    root = kitti_copy(tmp_path)
    out = tmp_path / "out"
    assert invoke("import", "kitti", root, "--out", out).exit_code == 0
    before = read_manifest(out)["content_hash"]
    (root / "training" / "label_2" / "000008.txt").write_text("Car 0 0 0 1 2 3 4\n")
    result = invoke("import", "kitti", root, "--out", out)
    assert result.exit_code == 1 and "000008.txt:1" in result.output
    assert read_manifest(out)["content_hash"] == before


# ---------------------------------------------------------------------------------------------
# nuScenes


@needs_fixtures
def test_nuscenes_csv_import(tmp_path):
    out = tmp_path / "nus"
    result = invoke(
        "import",
        "nuscenes",
        NUSCENES_SCAN,
        "--boxes-csv",
        NUSCENES / "boxes_lidar.csv",
        "--out",
        out,
    )
    assert result.exit_code == 0, result.output
    frames = FrameSet(out)
    assert frames.frame_ids == [NUSCENES_ID] and frames.sensor == "nuscenes"
    points = frames.frame(0)
    raw = np.fromfile(NUSCENES_SCAN, np.float32).reshape(-1, 5)
    assert len(points) == len(raw) == 34688
    np.testing.assert_allclose(points[:, 0], raw[:, 1])  # x forward = nuScenes y
    np.testing.assert_allclose(points[:, 1], -raw[:, 0])
    np.testing.assert_allclose(points[:, 3], raw[:, 3] / 255, rtol=1e-6)
    assert 0 <= points[:, 3].min() and points[:, 3].max() <= 1

    table = read_boxes(out)
    assert len(table) == 69
    cars = table.select(table["label"].astype(str) == "Car")
    assert len(cars) == 8
    listed = cars["num_lidar_pts"]
    assert np.all(np.abs(cars["num_points"] - listed) <= np.maximum(2, 0.1 * listed)), (
        cars["num_points"],
        listed,
    )
    np.testing.assert_array_equal(cars["num_points"], count_points_in_boxes(points, cars.boxes))
    # all objects: the in-box counts follow num_lidar_pts closely in total
    assert (
        abs(int(table["num_points"].sum()) - int(table["num_lidar_pts"].sum()))
        < 0.05 * table["num_lidar_pts"].sum()
    )


@needs_fixtures
def test_nuscenes_axes_option_only_rotates(tmp_path):
    forward, native = tmp_path / "fwd", tmp_path / "native"
    csv_path = NUSCENES / "boxes_lidar.csv"
    assert (
        invoke(
            "import", "nuscenes", NUSCENES_SCAN, "--boxes-csv", csv_path, "--out", forward
        ).exit_code
        == 0
    )
    result = invoke(
        "import",
        "nuscenes",
        NUSCENES_SCAN,
        "--boxes-csv",
        csv_path,
        "--lidar-frame",
        "--out",
        native,
    )
    assert result.exit_code == 0
    a, b = read_boxes(forward), read_boxes(native)
    np.testing.assert_array_equal(a["num_points"], b["num_points"])
    np.testing.assert_allclose(a.boxes[:, 0], b.boxes[:, 1])
    np.testing.assert_allclose(a.boxes[:, 1], -b.boxes[:, 0])
    np.testing.assert_allclose(np.cos(a.boxes[:, 6] - b.boxes[:, 6] + np.pi / 2), 1.0)


def _matrix_to_quaternion(matrix: np.ndarray) -> list[float]:
    """(w, x, y, z) of a rotation matrix (trace method; test rotations keep w well away from 0)."""
    w = np.sqrt(1 + np.trace(matrix)) / 2
    return [w, (matrix[2, 1] - matrix[1, 2]) / (4 * w), (matrix[0, 2] - matrix[2, 0]) / (4 * w),
            (matrix[1, 0] - matrix[0, 1]) / (4 * w)]  # fmt: skip


def _rotation(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k  # Rodrigues


def write_nuscenes_tables(
    root: Path, boxes: np.ndarray, categories: list[str], seed: int = 0
) -> None:
    """A one-sample v1.0 table set whose annotations are `boxes` (LiDAR frame, l w h) moved to a
    random global pose, stored the nuScenes way (global frame, w l h, quaternions)."""
    rng = np.random.default_rng(seed)
    (root / "samples" / "LIDAR_TOP").mkdir(parents=True)
    shutil.copy(NUSCENES_SCAN, root / "samples" / "LIDAR_TOP" / NUSCENES_SCAN.name)
    sensor_r = _rotation([0.01, -0.02, 1], -np.pi / 2 + 0.01)  # LIDAR_TOP in the ego frame
    sensor_t = np.array([0.94, 0.0, 1.84])
    ego_r = _rotation([0.02, 0.01, 1], rng.uniform(-3, 3))
    ego_t = rng.uniform(-2000, 2000, 3) * [1, 1, 0.01]
    to_global = ego_r @ sensor_r
    centres = boxes[:, :3] @ to_global.T + ego_r @ sensor_t + ego_t
    annotations = []
    for i, box in enumerate(boxes):
        box_r = to_global @ _rotation([0, 0, 1], box[6])
        annotations.append({
            "token": f"ann{i}", "sample_token": "s0", "instance_token": f"inst{i}",
            "translation": centres[i].tolist(), "size": [box[4], box[3], box[5]],
            "rotation": _matrix_to_quaternion(box_r), "num_lidar_pts": 7,
        })  # fmt: skip
    names = sorted(set(categories))
    tables = {
        "sensor": [{"token": "lidar", "channel": "LIDAR_TOP", "modality": "lidar"},
                   {"token": "cam", "channel": "CAM_FRONT", "modality": "camera"}],
        "calibrated_sensor": [{"token": "cs0", "sensor_token": "lidar", "translation": sensor_t.tolist(),
                               "rotation": _matrix_to_quaternion(sensor_r)},
                              {"token": "cs1", "sensor_token": "cam", "translation": [0, 0, 0],
                               "rotation": [1, 0, 0, 0]}],
        "ego_pose": [{"token": "ep0", "translation": ego_t.tolist(), "rotation": _matrix_to_quaternion(ego_r)}],
        "sample_data": [{"token": "sd0", "sample_token": "s0", "ego_pose_token": "ep0",
                         "calibrated_sensor_token": "cs0", "is_key_frame": True,
                         "filename": f"samples/LIDAR_TOP/{NUSCENES_SCAN.name}"},
                        {"token": "sd1", "sample_token": "s0", "ego_pose_token": "ep0",
                         "calibrated_sensor_token": "cs1", "is_key_frame": True,
                         "filename": "samples/CAM_FRONT/x.jpg"}],
        "sample": [{"token": "s0", "scene_token": "sc0", "timestamp": 1}],
        "scene": [{"token": "sc0", "name": "scene-0001"}],
        "category": [{"token": f"cat{j}", "name": name} for j, name in enumerate(names)],
        "instance": [{"token": f"inst{i}", "category_token": f"cat{names.index(c)}"} for i, c in enumerate(categories)],
        "sample_annotation": annotations,
    }  # fmt: skip
    (root / "v1.0-mini").mkdir()
    for name, rows in tables.items():
        (root / "v1.0-mini" / f"{name}.json").write_text(json.dumps(rows))


@needs_fixtures
def test_nuscenes_json_tables_match_lidar_frame_boxes(tmp_path):
    with open(NUSCENES / "boxes_lidar.csv") as handle:
        rows = list(csv.DictReader(handle))
    boxes = np.array([[float(r[c]) for c in "x y z l w h yaw".split()] for r in rows])
    categories = [
        "vehicle.car" if r["category"] == "car" else f"other.{r['category']}" for r in rows
    ]
    write_nuscenes_tables(tmp_path / "nuscenes", boxes, categories)
    out = tmp_path / "nus_json"
    result = invoke(
        "import",
        "nuscenes",
        tmp_path / "nuscenes",
        "--version",
        "v1.0-mini",
        "--lidar-frame",
        "--out",
        out,
    )
    assert result.exit_code == 0, result.output
    assert FrameSet(out).frame_ids == [NUSCENES_ID]
    table = read_boxes(out)
    np.testing.assert_allclose(table.boxes[:, :6], boxes[:, :6], atol=1e-6)
    np.testing.assert_allclose(
        np.angle(np.exp(1j * (table.boxes[:, 6] - boxes[:, 6]))), 0, atol=1e-6
    )
    labels = table["label"].astype(str)
    assert (labels == "Car").sum() == 8 and "other.pedestrian" in set(labels)
    # a configurable car category: pedestrians as Car instead
    out2 = tmp_path / "nus_ped"
    result = invoke(
        "import",
        "nuscenes",
        tmp_path / "nuscenes",
        "--car-category",
        "other.pedestrian",
        "--out",
        out2,
    )
    assert result.exit_code == 0, result.output
    assert (read_boxes(out2)["label"].astype(str) == "Car").sum() == sum(
        r["category"] == "pedestrian" for r in rows
    )
    # scene selection by name
    out3 = tmp_path / "nus_scene"
    result = invoke(
        "import", "nuscenes", tmp_path / "nuscenes", "--scenes", "scene-0001", "--out", out3
    )
    assert result.exit_code == 0 and len(FrameSet(out3)) == 1
    result = invoke(
        "import", "nuscenes", tmp_path / "nuscenes", "--scenes", "scene-9999", "--out", out3 / "x"
    )
    assert result.exit_code == 1 and "scene-9999" in result.output


@needs_fixtures
def test_nuscenes_truncated_scan_and_bad_csv(tmp_path):
    scan = tmp_path / "x.pcd.bin"
    scan.write_bytes(NUSCENES_SCAN.read_bytes()[:-16])  # 16 is not a multiple of 20
    out = tmp_path / "out"
    csv_path = tmp_path / "boxes.csv"
    csv_path.write_text("category,x,y,z,l,w,h,yaw\ncar,1,2,3,4,2,1.5,0\n")
    _expect_error(
        invoke("import", "nuscenes", scan, "--boxes-csv", csv_path, "--out", out),
        out,
        "x.pcd.bin",
        "20",
    )
    shutil.copy(NUSCENES_SCAN, scan)
    csv_path.write_text("category,x,y,z,l,w,h,yaw\ncar,1,2,3,4,2,1.5,0\ncar,1,2,x,4,2,1.5,0\n")
    _expect_error(
        invoke("import", "nuscenes", scan, "--boxes-csv", csv_path, "--out", out),
        out,
        "line 3",
        "'z'",
    )


# ---------------------------------------------------------------------------------------------
# OpenPCDet


@needs_fixtures
def test_openpcdet_round_trip(tmp_path):
    imported = tmp_path / "kitti_set"
    assert invoke("import", "kitti", KITTI, "--out", imported).exit_code == 0
    exported = tmp_path / "custom"
    result = invoke("export", "openpcdet", imported, "--split", "train", "--out", exported)
    assert result.exit_code == 0, result.output
    assert (exported / "ImageSets" / "train.txt").read_text().split() == ["000008"]
    lines = (exported / "labels" / "000008.txt").read_text().splitlines()
    assert len(lines) == 10 and all(len(line.split()) == 8 for line in lines)
    again = tmp_path / "again"
    result = invoke(
        "import", "openpcdet", exported, "--split", "train", "--sensor", "kitti", "--out", again
    )
    assert result.exit_code == 0, result.output
    np.testing.assert_array_equal(FrameSet(again).frame(0), FrameSet(imported).frame(0))
    a, b = read_boxes(imported), read_boxes(again)
    np.testing.assert_allclose(b.boxes, a.boxes, atol=1e-5)
    np.testing.assert_array_equal(b["label"], a["label"])
    np.testing.assert_array_equal(b["num_points"], a["num_points"])


def test_openpcdet_bad_label_and_class_mapping(tmp_path):
    root = tmp_path / "custom"
    (root / "points").mkdir(parents=True)
    (root / "labels").mkdir()
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-1, 1, (500, 3)) * [2, 1, 0.7] + [10, 0, -1], rng.uniform(0, 1, 500)]
    np.save(root / "points" / "a.npy", points.astype(np.float32))
    (root / "labels" / "a.txt").write_text(
        "10 0 -1 4 2 1.4 0.3 Vehicle\n20 5 -1 0.8 0.8 1.7 0 Pedestrian\n"
    )
    out = tmp_path / "out"
    result = invoke("import", "openpcdet", root, "--sensor", "kitti", "--out", out)
    assert result.exit_code == 0, result.output
    table = read_boxes(out)
    assert table["label"].tolist() == ["Car", "Pedestrian"]
    assert table["num_points"][0] == count_points_in_boxes(points, table.boxes[:1])[0] > 0
    (root / "labels" / "a.txt").write_text("10 0 -1 4 2 1.4 Vehicle\n")
    bad = tmp_path / "bad"
    _expect_error(
        invoke("import", "openpcdet", root, "--sensor", "kitti", "--out", bad),
        bad,
        "a.txt, line 1",
        "7 fields",
    )
    result = invoke("import", "openpcdet", root, "--sensor", "no-such-lidar", "--out", bad)
    assert result.exit_code == 1 and "no-such-lidar" in result.output and not bad.exists()
    # the one plausibility rule of every stage: a label 1e9 m away is corrupt, not a car
    (root / "labels" / "a.txt").write_text("10 0 1e9 4 2 1.4 0.3 Vehicle\n")
    _expect_error(
        invoke("import", "openpcdet", root, "--sensor", "kitti", "--out", bad), bad, "a.txt", "'a'"
    )


def test_quaternion_matrix_matches_rodrigues():
    rng = np.random.default_rng(1)
    for _ in range(20):
        axis, angle = rng.normal(size=3), rng.uniform(-3, 3)
        r = _rotation(axis, angle)
        half = angle / 2
        q = np.r_[np.cos(half), np.sin(half) * axis / np.linalg.norm(axis)]
        np.testing.assert_allclose(nuscenes.quaternion_to_matrix(q[None])[0], r, atol=1e-12)
        np.testing.assert_allclose(nuscenes.quaternion_to_matrix(-3 * q[None])[0], r, atol=1e-12)


@needs_fixtures
def test_nuscenes_csv_frame_ids_group_rows(tmp_path):
    scans = tmp_path / "scans"
    scans.mkdir()
    for name in ("b", "a"):
        shutil.copy(NUSCENES_SCAN, scans / f"{name}.pcd.bin")
    with open(NUSCENES / "boxes_lidar.csv") as handle:
        rows = list(csv.DictReader(handle))
    frame_of = ["b" if i % 3 == 0 else "a" for i in range(len(rows))]  # interleaved rows
    csv_path = tmp_path / "boxes.csv"
    with open(csv_path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=[*rows[0], "frame_id"])
        writer.writeheader()
        writer.writerows({**row, "frame_id": f} for row, f in zip(rows, frame_of, strict=True))
    out = tmp_path / "out"
    result = invoke(
        "import", "nuscenes", scans, "--boxes-csv", csv_path, "--lidar-frame", "--out", out
    )
    assert result.exit_code == 0, result.output
    assert FrameSet(out).frame_ids == ["a", "b"]
    table = read_boxes(out)
    for frame_id in ("a", "b"):
        expected = [
            [float(r[c]) for c in "x y z l w h".split()]
            for r, f in zip(rows, frame_of, strict=True)
            if f == frame_id
        ]
        np.testing.assert_allclose(table.for_frame(frame_id).boxes[:, :6], expected)
    # without a frame_id column several scans are ambiguous
    bad = tmp_path / "bad"
    result = invoke(
        "import", "nuscenes", scans, "--boxes-csv", NUSCENES / "boxes_lidar.csv", "--out", bad
    )
    assert result.exit_code == 1 and "frame_id" in result.output and not bad.exists()


@needs_fixtures
def test_nuscenes_tables_without_annotations_are_unlabeled(tmp_path):
    write_nuscenes_tables(tmp_path / "nuscenes", np.zeros((0, 7)), [])
    out = tmp_path / "out"
    result = invoke("import", "nuscenes", tmp_path / "nuscenes", "--out", out)
    assert result.exit_code == 0, result.output
    assert len(FrameSet(out)) == 1 and not (out / "boxes.parquet").exists()


@needs_fixtures
def test_kitti_other_types_and_id_list(tmp_path):
    root = kitti_copy(tmp_path)
    training = root / "training"
    for part, suffix in (("velodyne", ".bin"), ("calib", ".txt")):
        shutil.copy(training / part / f"000008{suffix}", training / part / f"000009{suffix}")
    car_line = (training / "label_2" / "000008.txt").read_text().splitlines()[3]
    van_line = "Van" + car_line[3:]
    (training / "label_2" / "000009.txt").write_text(
        f"{van_line}\nPedestrian 0 0 0 1 2 3 4 1.7 0.6 0.8 2 1.6 9 0\n"
    )
    ids = tmp_path / "val.txt"
    ids.write_text("000009\n")
    out = tmp_path / "out"
    result = invoke("import", "kitti", root, "--ids", ids, "--out", out)
    assert result.exit_code == 0, result.output
    assert FrameSet(out).frame_ids == ["000009"]
    table = read_boxes(out)
    assert table["label"].tolist() == ["Van", "Pedestrian"]
    assert invoke("import", "kitti", root, "--out", tmp_path / "all").exit_code == 0
    everything = read_boxes(tmp_path / "all")
    same_car = everything.select(np.flatnonzero(everything["frame_id"] == "000008")[3:4])
    np.testing.assert_allclose(table.boxes[0], same_car.boxes[0])  # a Van is converted like a Car
    assert table["num_points"][0] == same_car["num_points"][0] > 0
    ids.write_text("000009\n000010\n")
    bad = tmp_path / "bad"
    result = invoke("import", "kitti", root, "--ids", ids, "--out", bad)
    assert result.exit_code == 1 and "000010" in result.output and not bad.exists()
