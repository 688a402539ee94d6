"""Waymo import without TensorFlow: range images built from known points round-trip through v2
Parquet components and v1 Frame records; malformed inputs fail cleanly; only needed columns are
read."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.geometry import count_points_in_boxes
from dali_cli.importers.waymo import v1, v2
from dali_cli.importers.waymo.range_image import (
    column_azimuths,
    euler_to_rotation,
    row_inclinations,
    uniform_inclinations,
)
from dali_cli.store.artifacts import FrameSet, read_boxes

SEGMENT = "1005081002024129653_5313_150_5333_150"
STAMPS = (1_550_000_000_000_000, 1_550_000_000_100_000, 1_550_000_000_200_000)
TOP_H, TOP_W, FRONT_H, FRONT_W = 64, 180, 20, 60
# non-uniform TOP beams, lowest first, about -17.6 ... +2.4 degrees (denser near the horizon)
TOP_INCLINATIONS = np.radians(-17.6 + 20.0 * np.linspace(0, 1, TOP_H) ** 0.8)
SPEED_M_S = 10.0  # the car's speed along world x during the sweep


def transform(yaw=0.0, translation=(0.0, 0.0, 0.0), pitch=0.0):
    matrix = np.eye(4)
    matrix[:3, :3] = euler_to_rotation(np.float64(0.0), np.float64(pitch), np.float64(yaw))
    matrix[:3, 3] = translation
    return matrix


TOP_EXTRINSIC = transform(yaw=0.0314, translation=(1.43, 0.0, 2.184))
FRONT_EXTRINSIC = transform(yaw=0.02, translation=(4.07, 0.0, 0.69), pitch=0.3)
BOXES_VEHICLE = np.array(
    [[15.0, 3.0, 0.9, 4.5, 2.0, 1.7, 0.3], [-20.0, -8.0, 0.8, 4.2, 1.9, 1.6, -2.9],
     [30.0, -12.0, 1.0, 0.8, 0.7, 1.8, 1.2]]
)  # fmt: skip
BOX_TYPES = np.array([1, 1, 2])


def frame_pose(index: int) -> np.ndarray:
    return transform(yaw=0.1, translation=(100.0 + SPEED_M_S * 0.1 * index, 50.0, 3.0))


def pixel_time(cols: np.ndarray) -> np.ndarray:
    """Capture time of each column relative to the frame time, seconds (one sweep = 0.1 s)."""
    return (cols / TOP_W - 0.5) * 0.1


def synthetic_scan(rng, height, width, extrinsic, inclinations, index, rolling):
    """A range image (H, W, 4) with returns at random pixels, the truth points (vehicle frame at
    the frame time) and, with `rolling`, the per-pixel pose of a car moving during the sweep."""
    rows_inc = row_inclinations(height, inclinations, inclinations[0], inclinations[-1])
    image = np.full((height, width, 4), -1.0, np.float32)
    image[..., 2:] = 0
    valid = rng.random((height, width)) < 0.3
    rows, cols = np.nonzero(valid)
    distance = rng.uniform(2.0, 75.0, len(rows))
    image[rows, cols, 0] = distance
    image[rows, cols, 1] = rng.uniform(0.0, 3.0, len(rows))
    azimuth = column_azimuths(width, extrinsic)[cols]
    inclination = rows_inc[rows]
    # the ray in the LiDAR frame, written out independently of range_image_to_points
    direction = np.stack(
        [np.cos(inclination) * np.cos(azimuth), np.cos(inclination) * np.sin(azimuth),
         np.sin(inclination)], axis=1,
    )  # fmt: skip
    at_capture = (extrinsic[:3, :3] @ (direction * distance[:, None]).T).T + extrinsic[:3, 3]
    pose = None
    truth = at_capture
    if rolling:
        pose = np.zeros((height, width, 6), np.float32)
        base = frame_pose(index)
        offsets = SPEED_M_S * pixel_time(np.arange(width))  # (W,) metres along world x
        pose[..., 2] = 0.1  # yaw of the world_from_vehicle transforms
        pose[..., 3] = (base[0, 3] + offsets)[None, :]
        pose[..., 4], pose[..., 5] = base[1, 3], base[2, 3]
        # truth: the world point (seen at capture) expressed in the vehicle frame at frame time
        world = at_capture @ base[:3, :3].T + np.stack(
            [base[0, 3] + offsets[cols], np.full(len(cols), base[1, 3]),
             np.full(len(cols), base[2, 3])], axis=1,
        )  # fmt: skip
        truth = (world - base[:3, 3]) @ base[:3, :3]
    return image, truth, image[rows, cols, 1], pose


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    """Three frames: TOP (non-uniform beams, rolling shutter, both returns) and FRONT."""
    rng = np.random.default_rng(5)
    frames = []
    for index, stamp in enumerate(STAMPS):
        top1 = synthetic_scan(rng, TOP_H, TOP_W, TOP_EXTRINSIC, TOP_INCLINATIONS, index, True)
        # the second return has no pose of its own: Waymo applies return 1's (the same poses)
        top2 = synthetic_scan(rng, TOP_H, TOP_W, TOP_EXTRINSIC, TOP_INCLINATIONS, index, True)
        front = synthetic_scan(
            rng, FRONT_H, FRONT_W, FRONT_EXTRINSIC,
            uniform_inclinations(np.radians(-90.0), np.radians(30.0), FRONT_H), index, False,
        )  # fmt: skip
        frames.append({"stamp": stamp, "top1": top1, "top2": top2, "front": front})
    return frames


def ri_columns(component, ret, image):
    return {
        f"[{component}].range_image_return{ret}.values": image.reshape(-1).tolist(),
        f"[{component}].range_image_return{ret}.shape": list(image.shape),
    }


def waymo_field_type(name: str, inferred: pa.DataType) -> pa.DataType:
    """The Arrow type the dataset's v2 files use for a column (waymo_open_dataset/v2/
    perception/*.py and column_types.py; vehicle poses are float32[16] in the released files)."""
    if name == "key.laser_name" or name.endswith("].type"):
        return pa.int8()
    if name.endswith(".shape"):
        return pa.list_(pa.int32(), 3)
    if name.endswith("world_from_vehicle.transform"):
        return pa.list_(pa.float32(), 16)
    if name.endswith(".transform"):
        return pa.list_(pa.float64(), 16)
    if name.endswith("beam_inclination.values"):
        return pa.list_(pa.float64())
    if name.endswith(".values"):
        return pa.list_(pa.float32())
    return inferred


def write_component(rows: list[dict], path: Path, **options) -> None:
    """A v2 component file with the dataset's own column types (fixed-size lists included)."""
    table = pa.Table.from_pylist(rows)
    schema = pa.schema([pa.field(f.name, waymo_field_type(f.name, f.type)) for f in table.schema])
    pq.write_table(table.cast(schema), path, **options)


def write_v2(root: Path, frames, row_group_size=1) -> Path:
    """The five components of one segment as Waymo v2 Parquet files."""
    rows = []
    for f in frames:
        for laser, (first, second) in (
            (1, (f["top1"][0], f["top2"][0])),
            (2, (f["front"][0], None)),
        ):
            row = {"key.segment_context_name": SEGMENT, "key.frame_timestamp_micros": f["stamp"],
                   "key.laser_name": laser, **ri_columns("LiDARComponent", 1, first)}  # fmt: skip
            empty = np.full((1, 1, 4), -1.0, np.float32) if second is None else second
            row.update(ri_columns("LiDARComponent", 2, empty))
            row["[CameraDecoy].image"] = b"\0" * 64  # a column the importer must not read
            rows.append(row)
    for component in v2.COMPONENTS:
        (root / component).mkdir(parents=True, exist_ok=True)
    write_component(rows, root / "lidar" / f"{SEGMENT}.parquet", row_group_size=row_group_size)
    calibration = [
        {"key.segment_context_name": SEGMENT, "key.laser_name": 1,
         "[LiDARCalibrationComponent].extrinsic.transform": TOP_EXTRINSIC.reshape(-1).tolist(),
         "[LiDARCalibrationComponent].beam_inclination.min": float(TOP_INCLINATIONS[0]),
         "[LiDARCalibrationComponent].beam_inclination.max": float(TOP_INCLINATIONS[-1]),
         "[LiDARCalibrationComponent].beam_inclination.values": TOP_INCLINATIONS.tolist()},
        {"key.segment_context_name": SEGMENT, "key.laser_name": 2,
         "[LiDARCalibrationComponent].extrinsic.transform": FRONT_EXTRINSIC.reshape(-1).tolist(),
         "[LiDARCalibrationComponent].beam_inclination.min": float(np.radians(-90.0)),
         "[LiDARCalibrationComponent].beam_inclination.max": float(np.radians(30.0)),
         "[LiDARCalibrationComponent].beam_inclination.values": None},
    ]  # fmt: skip
    write_component(calibration, root / "lidar_calibration" / f"{SEGMENT}.parquet")
    poses = [{"key.segment_context_name": SEGMENT, "key.frame_timestamp_micros": f["stamp"],
              "[VehiclePoseComponent].world_from_vehicle.transform":
              frame_pose(i).reshape(-1).tolist()} for i, f in enumerate(frames)]  # fmt: skip
    write_component(poses, root / "vehicle_pose" / f"{SEGMENT}.parquet")
    pixel = [{"key.segment_context_name": SEGMENT, "key.frame_timestamp_micros": f["stamp"],
              "key.laser_name": 1, **ri_columns("LiDARPoseComponent", 1, f["top1"][3])}
             for f in frames]  # fmt: skip
    write_component(pixel, root / "lidar_pose" / f"{SEGMENT}.parquet")
    boxes = []
    for f in frames:
        for k, (box, kind) in enumerate(zip(BOXES_VEHICLE, BOX_TYPES, strict=True)):
            boxes.append({
                "key.segment_context_name": SEGMENT, "key.frame_timestamp_micros": f["stamp"],
                "key.laser_object_id": f"obj{k}",
                **{f"[LiDARBoxComponent].box.center.{a}": box[i] for i, a in enumerate("xyz")},
                **{f"[LiDARBoxComponent].box.size.{a}": box[3 + i] for i, a in enumerate("xyz")},
                "[LiDARBoxComponent].box.heading": box[6], "[LiDARBoxComponent].type": int(kind),
                "[LiDARBoxComponent].num_lidar_points_in_box": 100 + k,
                "[LiDARBoxComponent].num_top_lidar_points_in_box": 90 + k})  # fmt: skip
    write_component(boxes, root / "lidar_box" / f"{SEGMENT}.parquet")
    return root


def compressed_matrix(array: np.ndarray) -> bytes:
    matrix = v1.message_classes()["MatrixFloat"]()
    matrix.data.extend(array.reshape(-1).tolist())
    matrix.shape.dims.extend(array.shape)
    return zlib.compress(matrix.SerializeToString())


def write_v1(root: Path, frames) -> Path:
    classes = v1.message_classes()
    records = []
    for i, f in enumerate(frames):
        frame = classes["Frame"]()
        frame.context.name = SEGMENT
        frame.timestamp_micros = f["stamp"]
        frame.pose.transform.extend(frame_pose(i).reshape(-1).tolist())
        for name, extrinsic, values, low, high in (
            (1, TOP_EXTRINSIC, TOP_INCLINATIONS, TOP_INCLINATIONS[0], TOP_INCLINATIONS[-1]),
            (2, FRONT_EXTRINSIC, [], np.radians(-90.0), np.radians(30.0)),
        ):
            calibration = frame.context.laser_calibrations.add(name=name)
            calibration.extrinsic.transform.extend(extrinsic.reshape(-1).tolist())
            calibration.beam_inclinations.extend(list(values))
            calibration.beam_inclination_min, calibration.beam_inclination_max = low, high
        top = frame.lasers.add(name=1)
        top.ri_return1.range_image_compressed = compressed_matrix(f["top1"][0])
        top.ri_return1.range_image_pose_compressed = compressed_matrix(f["top1"][3])
        top.ri_return2.range_image_compressed = compressed_matrix(f["top2"][0])
        front = frame.lasers.add(name=2)
        front.ri_return1.range_image_compressed = compressed_matrix(f["front"][0])
        for k, (box, kind) in enumerate(zip(BOXES_VEHICLE, BOX_TYPES, strict=True)):
            label = frame.laser_labels.add(type=int(kind), id=f"obj{k}",
                                           num_lidar_points_in_box=100 + k)  # fmt: skip
            b = label.box
            b.center_x, b.center_y, b.center_z, b.length, b.width, b.height, b.heading = box
        records.append(frame.SerializeToString())
    root.mkdir(parents=True, exist_ok=True)
    v1.write_records(root / f"segment-{SEGMENT}_with_camera_labels.tfrecord", records)
    return root


def expected_top_frame(points_vehicle: np.ndarray) -> np.ndarray:
    return (points_vehicle - TOP_EXTRINSIC[:3, 3]) @ TOP_EXTRINSIC[:3, :3]


def run_import(root, out, *extra):
    return CliRunner().invoke(main, ["import", "waymo", str(root), "--out", str(out), *extra])


@pytest.mark.parametrize("fmt", ["v2", "v1"])
def test_points_and_boxes_round_trip(tmp_path, truth, fmt):
    root = write_v2(tmp_path / "v2", truth) if fmt == "v2" else write_v1(tmp_path / "v1", truth)
    out = tmp_path / "out"
    result = run_import(root, out, "--returns", "2", "--lidars", "all")
    assert result.exit_code == 0, result.output
    frames, boxes = FrameSet(out), read_boxes(out)
    assert len(frames) == len(STAMPS)
    for index, f in enumerate(truth):
        points = frames.frame(index)
        top1, top2, front = (expected_top_frame(f[k][1]) for k in ("top1", "top2", "front"))
        expected = np.concatenate([top1, top2, front])
        assert points.shape == (len(expected), 4)
        np.testing.assert_allclose(points[:, :3], expected, atol=1e-3)  # 1 mm
        np.testing.assert_allclose(points[: len(top1), :3], top1, atol=1e-3)
        intensities = np.concatenate([f["top1"][2], f["top2"][2], f["front"][2]])
        np.testing.assert_allclose(points[:, 3], np.tanh(intensities), atol=1e-6)
        assert len(top2) == len(f["top2"][2])
    # boxes: TOP frame, yaw minus the extrinsic's yaw, labels and dataset point counts kept
    first = boxes.for_frame(frames.frame_ids[0])
    np.testing.assert_allclose(first.boxes[:, :3], expected_top_frame(BOXES_VEHICLE[:, :3]),
                               atol=1e-6)  # fmt: skip
    np.testing.assert_allclose(first.boxes[:, 6], BOXES_VEHICLE[:, 6] - 0.0314, atol=1e-6)
    np.testing.assert_allclose(first.boxes[:, 3:6], BOXES_VEHICLE[:, 3:6])
    assert first["label"].tolist() == ["Car", "Car", "Pedestrian"]
    assert first["num_points"].tolist() == [100, 101, 102]
    assert frames.frame_ids[0] == f"{SEGMENT}_{STAMPS[0]}"
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["outputs"]["counts"]["segments"][next(iter(
        manifest["outputs"]["counts"]["segments"]))]["frames"] == 3  # fmt: skip


def test_a_point_inside_a_box_stays_inside_after_the_frame_change():
    from dali_cli.importers.waymo.frame import LaserCalibration, WaymoFrame, to_top_frame

    rng = np.random.default_rng(0)
    box = BOXES_VEHICLE[0]
    local = rng.uniform(-0.45, 0.45, (200, 3)) * box[3:6]
    c, s = np.cos(box[6]), np.sin(box[6])
    inside = np.stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1],
                       local[:, 2]], 1) + box[:3]  # fmt: skip
    frame = WaymoFrame("s", 0, None, {1: LaserCalibration(1, TOP_EXTRINSIC, None, 0, 0)}, [],
                       BOXES_VEHICLE[:1], np.ones(1), np.ones(1))  # fmt: skip
    points, boxes = to_top_frame(frame, np.column_stack([inside, np.zeros(len(inside))]))
    assert count_points_in_boxes(points, boxes)[0] == len(inside)


def test_uniform_inclinations_and_the_forward_column():
    """Waymo's conventions: uniform beams at bin centres, row 0 the highest beam, and the middle
    column looking along the vehicle's +x once the extrinsic yaw is applied."""
    rows = row_inclinations(4, None, -0.4, 0.0)
    np.testing.assert_allclose(rows, [-0.05, -0.15, -0.25, -0.35])
    azimuths = column_azimuths(2000, TOP_EXTRINSIC)
    middle = azimuths[999:1001].mean() + 0.0314  # plus the extrinsic yaw: vehicle frame
    assert abs(middle) < np.pi / 2000
    assert azimuths[0] > azimuths[-1]  # columns sweep clockwise, from behind on the left


@pytest.mark.parametrize("damage", ["bad-crc", "truncated", "not-a-frame"])
def test_malformed_v1_records_fail_cleanly(tmp_path, truth, damage):
    root = write_v1(tmp_path / "v1", truth[:2])
    path = next(root.glob("*.tfrecord"))
    data = bytearray(path.read_bytes())
    if damage == "bad-crc":
        data[40] ^= 0xFF
    elif damage == "truncated":
        data = data[: len(data) - 100]
    else:
        record = b"\xff\xff\xff not a protobuf"
        v1.write_records(path, [record])
        data = bytearray(path.read_bytes())
    path.write_bytes(bytes(data))
    out = tmp_path / "out"
    result = run_import(root, out)
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert path.name in result.output and "record" in result.output
    assert not out.exists() and not list(tmp_path.glob("out.tmp-*"))


@pytest.mark.parametrize("damage", ["missing-component", "wrong-dtype", "missing-column"])
def test_malformed_v2_components_fail_cleanly(tmp_path, truth, damage):
    root = write_v2(tmp_path / "v2", truth[:2])
    if damage == "missing-component":
        (root / "lidar_calibration" / f"{SEGMENT}.parquet").unlink()
        named = ("lidar_calibration", SEGMENT)
    elif damage == "wrong-dtype":
        path = root / "lidar" / f"{SEGMENT}.parquet"
        table = pq.read_table(path).to_pylist()
        table[1]["[LiDARComponent].range_image_return1.values"] = [1.0, 2.0]  # shape says more
        pq.write_table(pa.Table.from_pylist(table), path)
        named = (SEGMENT, str(STAMPS[0]), "laser 2")
    else:
        path = root / "lidar_box" / f"{SEGMENT}.parquet"
        pq.write_table(pq.read_table(path).drop(["[LiDARBoxComponent].type"]), path)
        named = ("lidar_box", "[LiDARBoxComponent].type")
    out = tmp_path / "out"
    result = run_import(root, out, "--lidars", "all")
    assert result.exit_code == 1 and "Traceback" not in result.output, result.output
    assert all(n in result.output for n in named), result.output
    assert not out.exists()


def test_v2_reads_only_the_columns_it_needs(tmp_path, truth, monkeypatch):
    root = write_v2(tmp_path / "v2", truth)
    asked: list[str] = []
    real_row_group, real_read_table = pq.ParquetFile.read_row_group, pq.read_table

    def row_group(self, index, columns=None, **kwargs):
        assert columns is not None, "a whole row group was read"
        asked.extend(columns)
        return real_row_group(self, index, columns=columns, **kwargs)

    def read_table(path, columns=None, **kwargs):
        assert columns is not None, f"all of {path} was read"
        asked.extend(columns)
        return real_read_table(path, columns=columns, **kwargs)

    monkeypatch.setattr(pq.ParquetFile, "read_row_group", row_group)
    monkeypatch.setattr(pq, "read_table", read_table)
    result = run_import(root, tmp_path / "out")  # TOP, first return
    assert result.exit_code == 0, result.output
    assert not [c for c in asked if "CameraDecoy" in c or "range_image_return2" in c]
    assert "[LiDARComponent].range_image_return1.values" in asked


def test_every_k_and_segment_selection(tmp_path, truth):
    root = write_v2(tmp_path / "v2", truth)
    result = run_import(root, tmp_path / "out", "--every", "2", "--segments", SEGMENT)
    assert result.exit_code == 0, result.output
    assert FrameSet(tmp_path / "out").frame_ids == [f"{SEGMENT}_{STAMPS[0]}",
                                                    f"{SEGMENT}_{STAMPS[2]}"]  # fmt: skip
    unknown = run_import(root, tmp_path / "out2", "--segments", "nope")
    assert unknown.exit_code == 1 and "nope" in unknown.output
