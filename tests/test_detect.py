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
SCAN = KITTI / "velodyne" / "000008.bin"  # cropped to the camera's view
RAW_DATE = Path(__file__).resolve().parent / "fixtures" / "kitti_raw" / "2011_09_26"
RAW_SCANS = RAW_DATE / "2011_09_26_drive_0001_sync" / "velodyne_points" / "data"  # full 360°

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
    """The boxes are Detector.predict's at the model's scale.json, above --score-min, on the scan
    cropped to the front view the model was adapted on (its model.json)."""
    from dali_cli.detector import Detector
    from dali_cli.sensors import get_profile
    from dali_cli.store.scale_file import read_scale
    from stages.detect import crop_front

    _, out = detected
    table = read_boxes(out)
    detector = Detector.load(MODEL)
    assert detector.config.front_deg is not None  # adapted on camera-view crops
    points = crop_front(kitti_points(), detector.config.front_deg)
    mount = get_profile("kitti").mount_height_m
    ((boxes, scores),) = detector.predict([points], read_scale(MODEL).scale, mount)
    keep = scores >= 0.1
    assert len(table) == keep.sum() > 0
    np.testing.assert_allclose(table.boxes, boxes[keep], atol=1e-5)
    lines = (out / "lidar" / "000008.txt").read_text().splitlines()
    assert len(lines) == len(table) and lines[0].split()[7] == "Car"


def test_a_scan_as_bin_pcd_and_npy_gets_the_same_boxes(tmp_path):
    """.pcd and .npy carry no sensor: detect reads them at the ground of the sensor the model is
    for (model.json's config), the one a KITTI .bin is read at, so all three find the same boxes."""
    points = kitti_points()
    for kind in ("bin", "pcd", "npy"):
        (tmp_path / kind).mkdir()
    shutil.copy(SCAN, tmp_path / "bin" / "000008.bin")
    write_pcd(tmp_path / "pcd" / "000008.pcd", points, "binary")
    np.save(tmp_path / "npy" / "000008.npy", points)
    found = {}
    for kind in ("bin", "pcd", "npy"):
        out = tmp_path / f"out-{kind}"
        result = invoke("detect", tmp_path / kind, "--model", MODEL, "--score-min", "0.1",
                        "--no-progress", "--out", out)  # fmt: skip
        assert result.exit_code == 0, result.output
        found[kind] = read_boxes(out)
    assert len(found["bin"]) > 0
    for kind in ("pcd", "npy"):
        assert len(found[kind]) == len(found["bin"]), kind
        np.testing.assert_allclose(found[kind].boxes, found["bin"].boxes, atol=1e-5)
        np.testing.assert_allclose(found[kind]["score"], found["bin"]["score"], atol=1e-6)


def test_the_models_front_view_is_the_default_and_front_deg_overrides_it(tmp_path):
    """On full 360° scans, detect without --front-deg crops to model.json's front view and says
    so, as --front-deg with that view does; --front-deg 360 keeps every point and finds more."""
    import json

    front = json.loads((MODEL / "model.json").read_text())["config"]["front_deg"]
    scans = tmp_path / "scans"
    shutil.copytree(RAW_SCANS, scans)
    outputs, found = {}, {}
    for name, extra in (("default", []), ("explicit", ["--front-deg", front]),
                        ("full", ["--front-deg", 360])):  # fmt: skip
        result = invoke("detect", scans, "--model", MODEL, "--score-min", "0.1", *extra,
                        "--no-progress", "--out", tmp_path / name)  # fmt: skip
        assert result.exit_code == 0, result.output
        outputs[name], found[name] = result.output, read_boxes(tmp_path / name).boxes
    assert f"the front {front:g}° (the model's view" in outputs["default"]
    assert f"the front {front:g}° (--front-deg)" in outputs["explicit"]
    np.testing.assert_array_equal(found["explicit"], found["default"])
    assert "cover the full 360" not in outputs["default"]
    assert len(found["full"]) > len(found["default"]) > 0


def test_the_summary_counts_the_boxes_label_2_leaves_out(tmp_path):
    """With a calib, label_2 holds the boxes inside the image: the summary line says how many it
    holds and how many it left out, and boxes.parquet keeps them all."""
    import re

    scan = sorted(RAW_SCANS.glob("*.bin"))[0]  # a full 360° scan
    out = tmp_path / "out"
    result = invoke("detect", scan, "--model", MODEL, "--score-min", "0.1", "--front-deg", 360,
                    "--calib", RAW_DATE, "--no-progress", "--out", out)  # fmt: skip
    assert result.exit_code == 0, result.output
    summary = re.search(r"(\d+) boxes in 1 scans \((\d+) written to label_2, (\d+) outside the "
                        r"image left out\)", result.output)  # fmt: skip
    assert summary, result.output
    total, written, left_out = (int(v) for v in summary.groups())
    table = read_boxes(out)
    assert total == len(table) and written + left_out == total
    assert written == len((out / "label_2" / f"{scan.stem}.txt").read_text().splitlines())
    assert left_out > 0  # the full scan's boxes off the camera's view


def test_a_raw_drives_calib_file_is_refused_naming_the_date_folder(tmp_path):
    shutil.copy(SCAN, tmp_path / "000008.bin")
    date = RAW_DATE
    out = tmp_path / "out"
    result = invoke("detect", tmp_path, "--model", MODEL, "--calib",
                    date / "calib_velo_to_cam.txt", "--no-progress", "--out", out)  # fmt: skip
    assert result.exit_code == 1, result.output
    message = result.output.strip().splitlines()[-1]
    assert str(date / "calib_velo_to_cam.txt") in message and "Traceback" not in result.output
    assert f"pass its date folder ({date}" in message and "calib_cam_to_cam.txt" in message
    assert not out.exists()
    foreign = tmp_path / "notes.txt"
    foreign.write_text("calib_time: 15-Mar-2012 11:37:16\n")
    result = invoke("detect", tmp_path / "000008.bin", "--model", MODEL, "--calib", foreign,
                    "--no-progress", "--out", out)  # fmt: skip
    assert result.exit_code == 1 and str(foreign) in result.output
    assert "--calib takes a KITTI object calib file" in result.output and not out.exists()


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
