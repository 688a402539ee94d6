"""`dali detect` on a user's own scans: every format read into the same points, the model's own
boxes (what `dali eval` scores), label_2 with calib, and bad input refused with nothing written."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.importers.common import ImportFormatError
from dali_cli.importers.scans import ScanFile, find_scans, read_pcd, read_scan
from dali_cli.store.artifacts import read_boxes

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "kitti-hdl64e"
KITTI = Path(__file__).resolve().parent / "fixtures" / "real" / "kitti" / "training"
SCAN = KITTI / "velodyne" / "000008.bin"

pytestmark = pytest.mark.skipif(not SCAN.is_file(), reason="KITTI fixture not found")


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def kitti_points() -> np.ndarray:
    return np.fromfile(SCAN, "<f4").reshape(-1, 4)


def write_pcd(path: Path, points: np.ndarray, mode: str, fields=("x", "y", "z", "intensity")):
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(fields)}\nSIZE {' '.join(['4'] * len(fields))}\n"
        f"TYPE {' '.join(['F'] * len(fields))}\nCOUNT {' '.join(['1'] * len(fields))}\n"
        f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\n"
        f"DATA {mode}\n"
    )
    values = points[:, : len(fields)].astype("<f4")
    if mode == "ascii":
        body = "".join(" ".join(f"{v:.6f}" for v in row) + "\n" for row in values).encode()
    else:
        body = values.tobytes()
    path.write_bytes(header.encode() + body)


@pytest.mark.parametrize("mode", ["ascii", "binary"])
def test_pcd_reads_the_same_points_as_the_bin(tmp_path, mode):
    points = kitti_points()[:2000]
    write_pcd(tmp_path / "a.pcd", points, mode)
    read = read_pcd(tmp_path / "a.pcd")
    np.testing.assert_allclose(read, points, atol=1e-5)


def test_npy_and_nuscenes_layouts_read_into_the_x_forward_frame(tmp_path):
    points = kitti_points()[:500]
    np.save(tmp_path / "a.npy", points[:, :3])
    read = read_scan(ScanFile("a", tmp_path / "a.npy", "npy"))
    np.testing.assert_allclose(read[:, :3], points[:, :3])
    np.testing.assert_array_equal(read[:, 3], 0)
    right = np.c_[-points[:, 1], points[:, 0], points[:, 2:4], np.zeros(len(points))]  # x right
    right.astype("<f4").tofile(tmp_path / "b.pcd.bin")
    read = read_scan(find_scans(tmp_path / "b.pcd.bin")[0])
    np.testing.assert_allclose(read, points, atol=1e-6)


@pytest.fixture(scope="module")
def detected(tmp_path_factory):
    scans = tmp_path_factory.mktemp("scans")
    shutil.copy(SCAN, scans / "000008.bin")
    out = scans.parent / "detected"
    result = invoke("detect", scans, "--model", MODEL, "--score-min", "0.1", "--no-progress",
                    "--out", out)  # fmt: skip
    assert result.exit_code == 0, result.output
    return scans, out


def test_detect_writes_the_models_own_boxes(detected):
    """The boxes are Detector.predict's at the model's scale.json, above --score-min."""
    from dali_cli.detector import Detector
    from dali_cli.store.scale_file import read_scale

    _, out = detected
    table = read_boxes(out)
    detector = Detector.load(MODEL)
    ((boxes, scores),) = detector.predict([kitti_points()], read_scale(MODEL).scale, 1.73)
    keep = scores >= 0.1
    assert len(table) == keep.sum() > 0
    np.testing.assert_allclose(table.boxes, boxes[keep], atol=1e-5)
    lines = (out / "lidar" / "000008.txt").read_text().splitlines()
    assert len(lines) == len(table) and lines[0].split()[7] == "Car"


def test_detect_with_calib_writes_label_2_that_import_reads_back(detected, tmp_path):
    scans, first = detected
    out = tmp_path / "with_calib"
    result = invoke("detect", scans, "--model", MODEL, "--score-min", "0.1", "--calib",
                    KITTI / "calib" / "000008.txt", "--no-progress", "--out", out)  # fmt: skip
    assert result.exit_code == 0, result.output
    assert len((out / "label_2" / "000008.txt").read_text().splitlines()) >= 1
    again = invoke("detect", scans, "--model", MODEL, "--score-min", "0.1", "--calib",
                   KITTI / "calib" / "000008.txt", "--no-progress", "--out", out)  # fmt: skip
    assert again.exit_code == 0 and "up to date" in again.output


@pytest.mark.parametrize(
    "case",
    ["truncated-bin", "pcd-without-z", "empty-folder", "model-without-weights", "not-a-scan"],
)
def test_bad_input_is_one_line_naming_the_file_and_nothing_is_written(tmp_path, case):
    scans, model = tmp_path / "scans", MODEL
    scans.mkdir()
    named = scans
    if case == "truncated-bin":
        named = scans / "000001.bin"
        named.write_bytes(kitti_points()[:100].tobytes()[:-3])
    elif case == "pcd-without-z":
        named = scans / "a.pcd"
        write_pcd(named, kitti_points()[:10], "ascii", fields=("x", "y", "intensity"))
    elif case == "model-without-weights":
        shutil.copy(SCAN, scans / "000008.bin")
        model = tmp_path / "model"
        model.mkdir()
        (model / "model.json").write_text((MODEL / "model.json").read_text())
        named = model
    elif case == "not-a-scan":
        named = scans / "notes.txt"
        named.write_text("hello")
        scans = named
    out = tmp_path / "out"
    result = invoke("detect", scans, "--model", model, "--no-progress", "--out", out)
    assert result.exit_code == 1, result.output
    message = result.output.strip().splitlines()[-1]
    assert str(named) in message and "Traceback" not in result.output
    assert not out.exists()


def test_find_scans_refuses_two_scans_of_one_frame_id(tmp_path):
    shutil.copy(SCAN, tmp_path / "a.bin")
    np.save(tmp_path / "a.npy", kitti_points()[:10])
    with pytest.raises(ImportFormatError, match="share the frame id 'a'"):
        find_scans(tmp_path)
