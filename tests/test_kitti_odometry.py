"""`dali import kitti-odometry` on small sequences written here in the odometry devkit's and
SemanticKITTI's layouts: scans, times and poses land with the frames, the crops keep what they
say, and every malformed file is a one-line error naming it and its field, with nothing written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.store.artifacts import FrameSet
from dali_cli.store.sequence import (
    CAMERA_POSE_COLUMNS,
    SEQUENCE_TABLE,
    SequenceError,
    read_lidar_poses,
)

# camera 2's projection and the velodyne -> camera transform of an odometry calib.txt (sequence
# 04's, rounded)
P2 = [707.09, 0, 601.89, 46.89, 0, 707.09, 183.11, 0.11, 0, 0, 1, 0.0037]
TR = [-0.0019, -0.9999, -0.0101, -0.0048, -0.0068, 0.0101, -0.9999, -0.0786, 0.9999, -0.0018,
      -0.0068, -0.2721]  # fmt: skip
SCANS = (0, 1, 3)  # a part of the sequence: scan 2 is missing, as in a sample subset


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def write_calib(path: Path, p2=P2, tr=TR) -> None:
    numbers = lambda values: " ".join(str(v) for v in values)  # noqa: E731
    lines = [f"P{i}: {numbers(p2)}" for i in range(4)] + [f"Tr: {numbers(tr)}"]
    path.write_text("\n".join(lines) + "\n")


def scan_points(index: int) -> np.ndarray:
    """`(6, 4)` float32: ahead, behind, left, right, ahead-left at 30 deg, ahead-right at 50 deg."""
    points = np.array(
        [
            [10, 0, -1, 0.1],
            [-10, 0, -1, 0.2],
            [0, 10, -1, 0.3],
            [0, -10, -1, 0.4],
            [10 * np.cos(np.radians(30)), 10 * np.sin(np.radians(30)), -1, 0.5],
            [10 * np.cos(np.radians(50)), -10 * np.sin(np.radians(50)), -1, 0.6],
        ],
        np.float32,
    )
    points[:, :3] *= 1 + 0.1 * index  # each scan its own, at the same angles
    return points


def poses(count: int) -> np.ndarray:
    """`(count, 12)`: identity rotations, translation (0, 0, i) for line i."""
    rows = np.tile(np.eye(3, 4).reshape(-1), (count, 1))
    rows[:, 11] = np.arange(count)
    return rows


def write_dataset(root: Path, *, calib=True, times=True, devkit_poses=True) -> Path:
    """`root/sequences/07` with SCANS, calib.txt, times.txt (5 lines) and poses/07.txt (5)."""
    sequence = root / "sequences" / "07"
    (sequence / "velodyne").mkdir(parents=True)
    for index in SCANS:
        scan_points(index).tofile(sequence / "velodyne" / f"{index:06d}.bin")
    if calib:
        write_calib(sequence / "calib.txt")
    if times:
        (sequence / "times.txt").write_text("".join(f"{0.1 * i:e}\n" for i in range(5)))
    if devkit_poses:
        (root / "poses").mkdir()
        np.savetxt(root / "poses" / "07.txt", poses(5), fmt="%e")
    return sequence


@pytest.fixture
def sequence(tmp_path) -> Path:
    return write_dataset(tmp_path / "dataset")


def imported(sequence: Path, out: Path, *flags) -> Path:
    result = invoke("import", "kitti-odometry", sequence, *flags, "--out", out, "--no-progress")
    assert result.exit_code == 0, result.output
    return out


def test_scans_times_and_poses_of_every_scan(sequence, tmp_path):
    out = imported(sequence, tmp_path / "out")
    frames = FrameSet(out)
    assert frames.frame_ids == [f"{i:06d}" for i in SCANS]
    for index in SCANS:
        np.testing.assert_array_equal(frames.frame(f"{index:06d}"), scan_points(index))
    assert not (out / "boxes.parquet").exists()  # unlabeled
    table = pq.read_table(out / SEQUENCE_TABLE).to_pydict()
    assert table["frame_id"] == frames.frame_ids and table["index"] == list(SCANS)
    # line i of times.txt and of the poses is scan i's, also past the missing scan 2
    np.testing.assert_allclose(table["time_s"], [0.1 * i for i in SCANS])
    np.testing.assert_allclose(table["camera_pose_23"], SCANS)
    np.testing.assert_allclose(
        np.c_[[table[name] for name in CAMERA_POSE_COLUMNS]].T[:, :11], poses(4)[list(SCANS), :11]
    )
    assert "lidar_pose_00" in table  # calib.txt: the LiDAR poses are derived


def test_poses_beside_the_scans_win_and_an_explicit_file_wins_over_both(sequence, tmp_path):
    np.savetxt(sequence / "poses.txt", poses(4) * 2, fmt="%e")
    out = imported(sequence, tmp_path / "semantic")
    np.testing.assert_allclose(
        pq.read_table(out / SEQUENCE_TABLE)["camera_pose_00"].to_numpy(), 2.0
    )
    other = tmp_path / "other.txt"
    np.savetxt(other, poses(4) * 3, fmt="%e")
    out = imported(sequence, tmp_path / "explicit", "--poses", other)
    np.testing.assert_allclose(
        pq.read_table(out / SEQUENCE_TABLE)["camera_pose_00"].to_numpy(), 3.0
    )


def rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def rigid(rng, scale_m: float) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rotation(rng), rng.normal(0, scale_m, 3)
    return out


def test_lidar_poses_map_a_fixed_world_point_to_one_first_scan_point(tmp_path):
    """The devkit's convention: P_i takes camera 0 of scan i to camera 0 of scan 0, Tr takes
    velodyne to camera 0; a point fixed in the world, seen by each scan, lands on one point of
    scan 0's LiDAR frame through that scan's lidar pose (also for scans 1 and 3 of a part)."""
    rng = np.random.default_rng(4)
    tr = rigid(rng, 0.3)
    camera = np.stack([np.eye(4)] + [rigid(rng, 5.0) for _ in range(4)])  # P_0 = I
    sequence = write_dataset(tmp_path / "d", devkit_poses=False)
    write_calib(sequence / "calib.txt", tr=tr[:3].reshape(-1).tolist())
    np.savetxt(sequence / "poses.txt", camera[:, :3].reshape(5, 12), fmt="%.17g")
    out = imported(sequence, tmp_path / "out")
    frame_ids = [f"{i:06d}" for i in SCANS]
    lidar = read_lidar_poses(out, frame_ids)
    world_camera0 = np.array([3.0, -1.0, 12.0, 1.0])  # in camera 0 of scan 0
    expected = np.linalg.inv(tr) @ world_camera0  # in the LiDAR frame of scan 0
    for pose, i in zip(lidar, SCANS, strict=True):
        seen = np.linalg.inv(tr) @ np.linalg.inv(camera[i]) @ world_camera0  # scan i's LiDAR
        np.testing.assert_allclose(pose @ seen, expected, atol=1e-9)
    table = pq.read_table(out / SEQUENCE_TABLE)
    np.testing.assert_allclose(table["camera_pose_03"].to_numpy(), camera[list(SCANS), 0, 3])


def test_without_calib_there_are_camera_poses_but_no_lidar_poses(tmp_path):
    sequence = write_dataset(tmp_path / "d", calib=False)
    out = imported(sequence, tmp_path / "out")
    table = pq.read_table(out / SEQUENCE_TABLE)
    assert "camera_pose_00" in table.column_names and "lidar_pose_00" not in table.column_names
    with pytest.raises(SequenceError, match=r"sequence.parquet: column 'lidar_pose_00' missing"):
        read_lidar_poses(out, [f"{i:06d}" for i in SCANS])


def test_a_sequence_of_scans_only_has_no_sequence_table(tmp_path):
    sequence = write_dataset(tmp_path / "d", calib=False, times=False, devkit_poses=False)
    out = imported(sequence, tmp_path / "out")
    assert len(FrameSet(out)) == len(SCANS) and not (out / SEQUENCE_TABLE).exists()


def test_crop_fov_keeps_the_points_camera_2_sees(sequence, tmp_path):
    out = imported(sequence, tmp_path / "out", "--crop-fov")
    for index in SCANS:
        kept = FrameSet(out).frame(f"{index:06d}")
        # ahead and 30 deg to the left lie in the ~82 deg wide image; behind, the sides and
        # 50 deg to the right do not
        np.testing.assert_array_equal(kept, scan_points(index)[[0, 4]])


def test_crop_front_deg_keeps_an_azimuth_band(tmp_path):
    sequence = write_dataset(tmp_path / "d", calib=False)
    out = imported(sequence, tmp_path / "out", "--crop-front-deg", "110")
    for index in SCANS:
        points = scan_points(index)
        azimuth = np.degrees(np.abs(np.arctan2(points[:, 1], points[:, 0])))
        np.testing.assert_array_equal(FrameSet(out).frame(f"{index:06d}"), points[azimuth <= 55])


def assert_refused(result, out: Path, *words: str, exit_code: int = 1) -> None:
    """A one-line error (no traceback) naming `words`, and no output written."""
    assert result.exit_code == exit_code, result.output
    message = result.output.strip().splitlines()
    assert "Traceback" not in result.output and message, result.output
    for word in words:
        assert word in message[-1], (word, message)
    assert not out.exists() and not list(out.parent.glob(f"{out.name}.tmp-*"))


def test_crop_fov_without_calib_is_a_usage_error(tmp_path):
    sequence = write_dataset(tmp_path / "d", calib=False)
    out = tmp_path / "out"
    result = invoke("import", "kitti-odometry", sequence, "--crop-fov", "--out", out)
    assert_refused(result, out, "--crop-fov", "calib.txt", exit_code=2)
    result = invoke(
        "import", "kitti-odometry", sequence, "--crop-fov", "--crop-front-deg", "90", "--out", out
    )
    assert_refused(result, out, "--crop-fov", "--crop-front-deg", exit_code=2)


def replace_line(path: Path, number: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[number - 1] = text
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(
    ("case", "words"),
    [
        ("calib_p2_short", ["calib.txt", "line 3", "'P2'", "11 values"]),
        ("calib_tr_text", ["calib.txt", "line 5", "'Tr'", "non-numeric"]),
        ("calib_no_tr", ["calib.txt", "'Tr' missing"]),
        ("pose_short", ["07.txt", "line 2", "pose", "11 values"]),
        ("pose_text", ["07.txt", "line 4", "pose", "non-numeric"]),
        ("poses_too_few", ["07.txt", "3 pose lines", "scans up to 000003"]),
        ("times_too_few", ["times.txt", "2 timestamp lines", "scans up to 000003"]),
        ("times_nan", ["times.txt", "line 1", "NaN/inf"]),
        ("scan_truncated", ["000001.bin", "17 bytes", "multiple of 16"]),
        ("no_scans", ["velodyne", "no .bin scans"]),
    ],
)
def test_malformed_sequence_is_a_one_line_error_and_writes_nothing(tmp_path, case, words):
    sequence = write_dataset(tmp_path / "dataset")
    calib, times = sequence / "calib.txt", sequence / "times.txt"
    pose_file = tmp_path / "dataset" / "poses" / "07.txt"
    if case == "calib_p2_short":
        replace_line(calib, 3, "P2: " + " ".join(["1"] * 11))
    elif case == "calib_tr_text":
        replace_line(calib, 5, "Tr: " + " ".join(["1"] * 11) + " x")
    elif case == "calib_no_tr":
        replace_line(calib, 5, "")
    elif case == "pose_short":
        replace_line(pose_file, 2, " ".join(["1"] * 11))
    elif case == "pose_text":
        replace_line(pose_file, 4, " ".join(["1"] * 11) + " one")
    elif case == "poses_too_few":
        np.savetxt(pose_file, poses(3), fmt="%e")
    elif case == "times_too_few":
        times.write_text("0.0\n0.1\n")
    elif case == "times_nan":
        times.write_text("nan\n0.1\n0.2\n0.3\n")
    elif case == "scan_truncated":
        (sequence / "velodyne" / "000001.bin").write_bytes(b"\0" * 17)
    elif case == "no_scans":
        for path in (sequence / "velodyne").glob("*.bin"):
            path.unlink()
    out = tmp_path / "out"
    result = invoke("import", "kitti-odometry", sequence, "--out", out, "--no-progress")
    assert_refused(result, out, *words)
