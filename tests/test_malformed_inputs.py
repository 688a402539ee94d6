"""Fuzz-style: every importer and every stage that reads frames or boxes, fed malformed inputs
(NaN/inf, empty, wrong dtypes, hostile ids, missing and damaged Zarr chunks, malformed label lines,
calib files missing a matrix). Each must exit non-zero with a clean message (no traceback) that
names the file and the frame, row, line or field, and write nothing: no --out, no `.tmp-*`, no
file anywhere else.

Inputs are tiny: two toy frames (tests/toy_scenes.py), a detector trained for one epoch on
them, a two-car procedural library, and copies of the real KITTI / nuScenes test fixtures.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import zarr
from click.testing import CliRunner
from test_retrain import SMALL as SMALL_DETECTOR
from test_retrain import TOY as RETRAIN_TOY
from toy_scenes import write_toy_dataset

from dali_cli.cli import main
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import read_boxes, write_boxes

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "real"
KITTI_ROOT = FIXTURES / "kitti"
NUSCENES_SCAN = next((FIXTURES / "nuscenes").glob("*.pcd.bin"), None)
NUSCENES_CSV = FIXTURES / "nuscenes" / "boxes_lidar.csv"
HOSTILE = {  # name -> id; "ABS" is an absolute path into the case's directory
    "parent": "../../evil",
    "absolute": "ABS",
    "subdir": "a/b",
    "nul": "a\x00b",
    "dotdot": "..",
    "long": "x" * 300,
}
# the small detector and toy scene sizes of test_retrain, with fewer frames and rays
TOY = {**RETRAIN_TOY, "frames": 2, "cars_per_frame": 2, "beams": 16, "points_per_beam": 200}


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Valid inputs every case starts from (make_world)."""
    return make_world(tmp_path_factory.mktemp("world"))


def make_world(root: Path) -> Path:
    """Source, target (frames 000000, 000001, labels), a one-epoch detector (`root/model`,
    configured by `root/detector.json`) and a procedural library, under `root`."""
    write_toy_dataset(root / "source", get_profile("waymo"), seed=1, **TOY)
    write_toy_dataset(root / "target", get_profile("kitti"), seed=2, **TOY)
    (root / "detector.json").write_text(json.dumps(SMALL_DETECTOR))
    for args in (
        ["pretrain", "--source", root / "source", "--out", root / "model", "--epochs", "1",
         "--detector-config", root / "detector.json", "--no-progress"],
        ["library", "build", "--procedural", "2", "--out", root / "library"],
    ):  # fmt: skip
        result = invoke(*args)
        assert result.exit_code == 0, result.output
    return root


def snapshot(root: Path) -> dict[str, int]:
    """Every path under `root` with its size (directories: -1)."""
    return {
        str(p.relative_to(root)): (p.stat().st_size if p.is_file() else -1)
        for p in sorted(root.rglob("*"))
    }


def expect_refused(case: Path, args: list, *needles: str) -> None:
    """Run `dali args...`; it must fail cleanly, name every needle, and write nothing."""
    (case / "runs").mkdir(exist_ok=True)
    before = snapshot(case)
    result = invoke(*args)
    assert result.exit_code != 0, result.output
    assert isinstance(result.exception, SystemExit), (
        f"traceback instead of an error message: {result.exception!r}\n{result.output}"
    )
    assert "Traceback" not in result.output
    for needle in needles:
        assert needle in result.output, (needle, result.output)
    assert snapshot(case) == before, "something was written"


# ---------------------------------------------------------------------------------------------
# malformed frame sets and box tables


def copy_target(world: Path, case: Path) -> Path:
    target = case / "target"
    shutil.copytree(world / "target", target)
    return target


def damage_frames(world: Path, case: Path, how: str) -> tuple[Path, tuple[str, ...]]:
    """A copy of the target frame set damaged `how`; returns it and what the error must name."""
    target = copy_target(world, case)
    store = target / "frames.zarr"
    chunk = store / "points" / "c" / "0" / "0"
    if how == "missing-chunk":
        chunk.unlink()
        return target, ("frames.zarr", "c/0/0", "missing", "'000000'")
    if how == "truncated-chunk":
        chunk.write_bytes(chunk.read_bytes()[: chunk.stat().st_size // 2])
        return target, ("frames.zarr", "c/0/0", "cannot be decoded", "'000000'")
    if how == "garbage-chunk":
        chunk.write_bytes(b"\x28\xb5\x2f\xfd" + bytes(range(256)) * 4)
        return target, ("frames.zarr", "c/0/0", "cannot be decoded", "'000000'")
    if how == "missing-offsets":
        shutil.rmtree(store / "offsets" / "c")
        return target, ("frames.zarr/offsets", "chunks missing")
    if how == "missing-frame-ids":
        shutil.rmtree(store / "frame_ids" / "c")
        return target, ("frames.zarr/frame_ids", "chunks missing")
    if how == "truncated-offsets":
        (store / "offsets" / "c" / "0").write_bytes(b"\x28\xb5\x2f\xfd\x00")
        return target, ("frames.zarr/offsets", "cannot be read")
    if how == "garbage-metadata":
        (store / "points" / "zarr.json").write_text('{"zarr_format": 3, "node_type": "arr')
        return target, ("frames.zarr/points/zarr.json", "not valid JSON")
    group = zarr.open_group(str(store), mode="r+")
    if how == "nan-points":
        points = group["points"]
        values = points[:]
        values[2700, 1] = np.inf  # in frame 000001 (frames have 2,600 points)
        points[:] = values
        return target, ("frames.zarr", "frame '000001'", "NaN/inf")
    if how == "float64-points":
        values = group["points"][:]
        del group["points"]
        group.create_array("points", data=values.astype(np.float64))
        return target, ("frames.zarr/points", "float32", "float64")
    if how.startswith("id-"):
        frame_id = HOSTILE[how[3:]]
        frame_id = str(case / "abs") if frame_id == "ABS" else frame_id
        group["frame_ids"][:] = np.asarray(["000000", frame_id], dtype=object)
        return target, ("frames.zarr/frame_ids", "frame 1", "frame id")
    raise ValueError(how)


def damage_boxes(world: Path, case: Path, how: str) -> tuple[Path, tuple[str, ...]]:
    """A box table (directory) damaged `how`; returns it and what the error must name."""
    boxes = case / "boxes"
    boxes.mkdir()
    path = boxes / "boxes.parquet"
    arrow = pq.read_table(world / "target" / "boxes.parquet")
    column = arrow.column_names.index

    def replaced(name, values, type_=None):
        return arrow.set_column(column(name), name, pa.array(values, type_))

    rows = arrow.num_rows
    if how == "garbage":
        path.write_bytes(b"PAR1 not really parquet")
        return boxes, ("boxes.parquet", "Parquet")
    if how == "empty-file":
        path.write_bytes(b"")
        return boxes, ("boxes.parquet",)
    if how == "nan-box":
        x = arrow.column("x").to_numpy().copy()
        x[2] = np.nan
        table = replaced("x", x)
        need = ("boxes.parquet", "row 2", "NaN/inf")
    elif how == "nan-score":
        score = arrow.column("score").to_numpy().copy()
        score[1] = np.nan
        table = replaced("score", score)
        need = ("boxes.parquet", "row 1", "NaN/inf score")
    elif how == "negative-size":
        length = arrow.column("l").to_numpy().copy()
        length[1] = -4.0
        table = replaced("l", length)
        need = ("boxes.parquet", "row 1", "negative size")
    elif how == "num-points-2**40":
        table = replaced("num_points", [1] * (rows - 1) + [2**40], pa.int64())
        need = ("boxes.parquet", "num_points", f"row {rows - 1}", str(2**40))
    elif how == "frame-id-int":
        table = replaced("frame_id", list(range(rows)), pa.int64())
        need = ("boxes.parquet", "frame_id", "string")
    elif how == "missing-column":
        table = arrow.drop_columns(["yaw"])
        need = ("boxes.parquet", "missing column 'yaw'")
    elif how.startswith("id-"):
        frame_id = HOSTILE[how[3:]]
        frame_id = str(case / "abs") if frame_id == "ABS" else frame_id
        ids = arrow.column("frame_id").to_pylist()
        ids[1] = frame_id
        table = replaced("frame_id", ids, pa.string())
        need = ("boxes.parquet", "row 1", "frame id")
    else:
        raise ValueError(how)
    pq.write_table(table, path)
    return boxes, need


FRAME_DAMAGE = [
    "missing-chunk",
    "truncated-chunk",
    "garbage-chunk",
    "missing-offsets",
    "missing-frame-ids",
    "truncated-offsets",
    "garbage-metadata",
    "nan-points",
    "float64-points",
    *(f"id-{name}" for name in HOSTILE),
]
BOX_DAMAGE = [
    "garbage",
    "empty-file",
    "nan-box",
    "nan-score",
    "negative-size",
    "num-points-2**40",
    "frame-id-int",
    "missing-column",
    *(f"id-{name}" for name in HOSTILE),
]
OUT = ("runs", "out")


def out_of(case: Path) -> Path:
    return case.joinpath(*OUT)


# each: (world, case, damaged input) -> dali arguments
FRAME_STAGES: dict[str, Callable[[Path, Path, Path], list]] = {
    "pseudo-label": lambda w, c, t: [
        "pseudo-label", "--model", w / "model", "--data", t, "--scale", "1", "--out",
        out_of(c), "--no-progress"],
    "ppcg-rc": lambda w, c, t: [
        "ppcg-rc", "--data", t, "--boxes", w / "target", "--library", w / "library", "--out",
        out_of(c), "--no-progress"],
    "ppcg-cf": lambda w, c, t: [
        "ppcg-cf", "--data", t, "--boxes", w / "target", "--library", w / "library", "--out",
        out_of(c), "--no-progress"],
    "ptsn-sweep": lambda w, c, t: [
        "ptsn-sweep", "--model", w / "model", "--data", t, "--out", out_of(c), "--no-progress"],
    "eval-model": lambda w, c, t: [
        "eval", "--model", w / "model", "--data", t, "--scale", "1",
        "--out", out_of(c) / "metrics.json"],
    "view": lambda w, c, t: ["view", t, "--frame", "000001", "--out", out_of(c) / "v.png"],
    "export-openpcdet": lambda w, c, t: ["export", "openpcdet", t, "--out", out_of(c)],
    "retrain": lambda w, c, t: [
        "retrain", "--init", w / "model", "--source", w / "source", "--ppcg", t,
        "--epochs", "0.5", "--out", out_of(c), "--no-progress"],
}  # fmt: skip
BOX_STAGES: dict[str, Callable[[Path, Path, Path], list]] = {
    "ppcg-rc": lambda w, c, b: [
        "ppcg-rc", "--data", w / "target", "--boxes", b, "--library", w / "library", "--out",
        out_of(c), "--no-progress"],
    "ppcg-cf": lambda w, c, b: [
        "ppcg-cf", "--data", w / "target", "--boxes", b, "--library", w / "library", "--out",
        out_of(c), "--no-progress"],
    "eval-pred": lambda w, c, b: [
        "eval", "--pred", b, "--gt", w / "target", "--out", out_of(c) / "metrics.json"],
    "eval-gt": lambda w, c, b: [
        "eval", "--pred", w / "target", "--gt", b, "--out", out_of(c) / "metrics.json"],
    "view": lambda w, c, b: [
        "view", w / "target", "--frame", "000000", "--boxes", b, "--out", out_of(c) / "v.png"],
    "export-kitti": lambda w, c, b: [
        "export", "kitti", b, "--calib-root", kitti_calib(c), "--out", out_of(c)],
    "export-openpcdet": lambda w, c, b: [
        "export", "openpcdet", w / "target", "--boxes", b, "--out", out_of(c)],
    "retrain": lambda w, c, b: [
        "retrain", "--init", w / "model", "--source", w / "source", "--ppcg",
        ppcg_with_boxes(w, c, b), "--epochs", "0.5", "--out", out_of(c), "--no-progress"],
}  # fmt: skip


def kitti_calib(case: Path) -> Path:
    """A calib directory for the toy frames (the real fixture's matrices), plus one file where
    an escaping id's calib lookup would land."""
    calib = case / "calib"
    if not calib.is_dir():
        calib.mkdir()
        text = (KITTI_ROOT / "training" / "calib" / "000008.txt").read_text()
        for frame_id in ("000000", "000001"):
            (calib / f"{frame_id}.txt").write_text(text)
        (case / "evil.txt").write_text(text)
    return calib


def ppcg_with_boxes(world: Path, case: Path, boxes: Path) -> Path:
    """A PPCG-like training set: the target's frames with the damaged box table."""
    ppcg = case / "ppcg"
    shutil.copytree(world / "target" / "frames.zarr", ppcg / "frames.zarr")
    shutil.copy(boxes / "boxes.parquet", ppcg / "boxes.parquet")
    return ppcg


def stage_cases() -> list[tuple[str, str, str]]:
    """(input kind, stage, damage); retrain (a model load per case) gets one hostile id only."""
    cases = [("frames", stage, how) for stage in FRAME_STAGES for how in FRAME_DAMAGE]
    cases += [("boxes", stage, how) for stage in BOX_STAGES for how in BOX_DAMAGE]
    return [
        (kind, stage, how)
        for kind, stage, how in cases
        if not (stage == "retrain" and how.startswith("id-") and how != "id-parent")
    ]


@pytest.mark.parametrize(("kind", "stage", "how"), stage_cases())
def test_stages_refuse_damaged_inputs(world, tmp_path, kind, stage, how):
    damage, stages = (
        (damage_frames, FRAME_STAGES) if kind == "frames" else (damage_boxes, BOX_STAGES)
    )
    damaged, needles = damage(world, tmp_path, how)
    expect_refused(tmp_path, stages[stage](world, tmp_path, damaged), *needles)


def test_empty_pseudo_labels_flow_through_ppcg_view_and_retrain(world, tmp_path):
    """A run whose pseudo-label cut keeps no box still goes on."""
    pseudo, rc = tmp_path / "pseudo", tmp_path / "rc"
    steps = [
        ["pseudo-label", "--model", world / "model", "--data", world / "target", "--scale",
         "1", "--score-min", "1.0", "--out", pseudo, "--no-progress"],
        ["ppcg-rc", "--data", world / "target", "--boxes", pseudo, "--library",
         world / "library", "--out", rc, "--no-progress"],
        ["view", rc, "--frame", "000000", "--out", tmp_path / "v.png"],
        ["eval", "--pred", rc, "--gt", world / "target", "--out", tmp_path / "m.json"],
        ["retrain", "--init", world / "model", "--source", world / "source", "--ppcg", rc,
         "--epochs", "0.5", "--out", tmp_path / "model", "--no-progress"],
    ]  # fmt: skip
    for step in steps:
        result = invoke(*step)
        assert result.exit_code == 0, (step[0], result.output)
    assert len(read_boxes(rc)) == 0
    schema = pq.read_schema(rc / "boxes.parquet")
    assert all(not pa.types.is_null(field.type) for field in schema), schema


def test_pretrain_refuses_an_absurd_box(world, tmp_path):
    source = tmp_path / "source"
    shutil.copytree(world / "source", source)
    table = read_boxes(source)
    table.columns["l"][0] = 1e30
    write_boxes(source, table)
    expect_refused(
        tmp_path,
        ["pretrain", "--source", source, "--out", out_of(tmp_path), "--epochs", "1",
         "--detector-config", world / "detector.json", "--no-progress"],
        "boxes.parquet", "row 0",
    )  # fmt: skip


def test_eval_refuses_a_model_that_is_not_dali(world, tmp_path):
    model = tmp_path / "model"
    shutil.copytree(world / "model", model)
    (model / "model.pt").write_bytes(b"not a checkpoint at all")
    expect_refused(
        tmp_path,
        ["eval", "--model", model, "--data", world / "target", "--scale", "1", "--out",
         out_of(tmp_path) / "metrics.json"],
        "model.pt",
    )  # fmt: skip


# ---------------------------------------------------------------------------------------------
# importers


def kitti_copy(case: Path) -> Path:
    root = case / "kitti"
    shutil.copytree(KITTI_ROOT, root)
    for path in root.rglob("*"):
        path.chmod(0o755 if path.is_dir() else 0o644)
    return root / "training"


def _edit_line(path: Path, edit: Callable[[list[str]], list[str]], line: int = 0) -> None:
    lines = path.read_text().splitlines()
    lines[line] = " ".join(edit(lines[line].split()))
    path.write_text("\n".join(lines) + "\n")


def _drop_calib_key(path: Path, key: str) -> None:
    lines = [line for line in path.read_text().splitlines() if not line.startswith(key)]
    path.write_text("\n".join(lines) + "\n")


def kitti_case(case: Path, how: str) -> tuple[list, tuple[str, ...]]:
    split = kitti_copy(case)
    scan, label, calib = (
        split / "velodyne" / "000008.bin",
        split / "label_2" / "000008.txt",
        split / "calib" / "000008.txt",
    )
    extra: list = []
    if how == "truncated-scan":
        scan.write_bytes(scan.read_bytes()[:-6])
        need: tuple = ("000008.bin", "not a multiple of 16")
    elif how == "nan-scan":
        points = np.fromfile(scan, "<f4").reshape(-1, 4)
        points[17, 2] = np.nan
        points.tofile(scan)
        need = ("000008.bin", "point 17", "NaN/inf")
    elif how == "empty-velodyne":
        scan.unlink()
        need = ("velodyne", "no .bin scans")
    elif how == "label-14-fields":
        _edit_line(label, lambda f: f[:14])
        need = ("000008.txt:1", "got 14")
    elif how == "label-not-a-number":
        _edit_line(label, lambda f: f[:9] + ["wide"] + f[10:], line=1)
        need = ("000008.txt:2", "'wide'", "not a number")
    elif how == "label-nan":
        _edit_line(label, lambda f: f[:11] + ["nan"] + f[12:])
        need = ("000008.txt:1", "non-finite")
    elif how == "label-inf-size":
        _edit_line(label, lambda f: f[:8] + ["inf"] + f[9:], line=2)
        need = ("000008.txt:3", "non-finite")
    elif how == "label-occluded-2**40":
        _edit_line(label, lambda f: f[:2] + [str(2**40)] + f[3:])
        need = ("000008.txt:1", "occluded")
    elif how == "label-binary":
        label.write_bytes(b"\xff\xfe\x00Car 0 0")
        need = ("000008.txt", "not UTF-8")
    elif how == "calib-binary":
        calib.write_bytes(b"P2: \xff\xfe")
        need = ("calib/000008.txt", "not UTF-8")
    elif how == "calib-missing-matrix":
        _drop_calib_key(calib, "Tr_velo_to_cam")
        need = ("calib/000008.txt", "Tr_velo_to_cam", "missing")
    elif how == "calib-short-matrix":
        _edit_line(calib, lambda f: f[:-2], line=5)
        need = ("calib/000008.txt", "line 6", "values, expected 12")
    elif how == "calib-nan":
        _edit_line(calib, lambda f: f[:3] + ["nan"] + f[4:], line=2)
        need = ("calib/000008.txt", "line 3", "NaN/inf")
    elif how.startswith("ids-"):
        frame_id = HOSTILE[how[4:]]
        frame_id = str(case / "abs") if frame_id == "ABS" else frame_id
        if how == "ids-parent":  # an id that would reach another dataset's velodyne folder
            other = case / "other" / "training" / "velodyne"
            other.mkdir(parents=True)
            shutil.copy(scan, other / "000009.bin")
            frame_id = "../../other/training/velodyne/000009"
        ids = case / "ids.txt"
        ids.write_text(f"000008\n{frame_id}\n")
        extra = ["--ids", ids]
        need = ("ids.txt", "line 2", "frame id")
    else:
        raise ValueError(how)
    return ["import", "kitti", split, *extra, "--out", out_of(case)], need


KITTI_DAMAGE = [
    "truncated-scan",
    "nan-scan",
    "empty-velodyne",
    "label-14-fields",
    "label-not-a-number",
    "label-nan",
    "label-inf-size",
    "label-occluded-2**40",
    "label-binary",
    "calib-binary",
    "calib-missing-matrix",
    "calib-short-matrix",
    "calib-nan",
    *(f"ids-{name}" for name in HOSTILE if name != "nul"),  # a NUL cannot be in a text line
]


@pytest.mark.parametrize("how", KITTI_DAMAGE)
def test_import_kitti_refuses_malformed_files(tmp_path, how):
    args, needles = kitti_case(tmp_path, how)
    expect_refused(tmp_path, args, *needles)


def nuscenes_csv_case(case: Path, how: str) -> tuple[list, tuple[str, ...]]:
    scans = case / "scans"
    scans.mkdir()
    scan = scans / NUSCENES_SCAN.name
    shutil.copy(NUSCENES_SCAN, scan)
    csv = case / "boxes.csv"
    lines = NUSCENES_CSV.read_text().splitlines()
    header, rows = lines[0], lines[1:4]
    frame_id = NUSCENES_SCAN.name.removesuffix(".pcd.bin")
    path_arg: Path = scans
    if how == "nan":
        rows[1] = ",".join(rows[1].split(",")[:2] + ["nan"] + rows[1].split(",")[3:])
        need: tuple = ("boxes.csv", "line 3", "column 'y'")
    elif how == "inf-size":
        rows[2] = ",".join(rows[2].split(",")[:4] + ["inf"] + rows[2].split(",")[5:])
        need = ("boxes.csv", "line 4", "column 'l'")
    elif how == "num-lidar-pts-2**40":
        rows[0] = ",".join(rows[0].split(",")[:-1] + [str(2**40)])
        need = ("boxes.csv", "line 2", "num_lidar_pts", "int32")
    elif how == "missing-column":
        header = header.replace(",yaw", "")
        rows = [",".join(r.split(",")[:7] + r.split(",")[8:]) for r in rows]
        need = ("boxes.csv", "missing column 'yaw'")
    elif how == "short-row":
        rows[1] = ",".join(rows[1].split(",")[:5])
        need = ("boxes.csv", "line 3", "fields")
    elif how == "binary":
        rows[1] = "car,\udcff\udcfe"
        need = ("boxes.csv", "cannot read CSV")
    elif how == "truncated-scan":
        scan.write_bytes(scan.read_bytes()[:-3])
        need = (NUSCENES_SCAN.name, "not a multiple of 20")
    elif how.startswith("id-"):
        hostile = HOSTILE[how[3:]]
        hostile = str(case / "abs") if hostile == "ABS" else hostile
        header += ",frame_id"
        rows = [f"{r},{frame_id}" for r in rows]
        rows[2] = f"{rows[2].rsplit(',', 1)[0]},{hostile}"
        need = ("boxes.csv", "line 4", "frame_id", "frame id")
    else:
        raise ValueError(how)
    csv.write_bytes(("\n".join([header, *rows]) + "\n").encode("utf-8", "surrogateescape"))
    return ["import", "nuscenes", path_arg, "--boxes-csv", csv, "--out", out_of(case)], need


NUSCENES_CSV_DAMAGE = [
    "nan",
    "inf-size",
    "num-lidar-pts-2**40",
    "missing-column",
    "short-row",
    "binary",
    "truncated-scan",
    *(f"id-{name}" for name in HOSTILE),
]


@pytest.mark.skipif(NUSCENES_SCAN is None, reason="nuScenes fixture scan missing")
@pytest.mark.parametrize("how", NUSCENES_CSV_DAMAGE)
def test_import_nuscenes_csv_refuses_malformed_files(tmp_path, how):
    args, needles = nuscenes_csv_case(tmp_path, how)
    expect_refused(tmp_path, args, *needles)


def nuscenes_tables(case: Path, mutate: Callable[[dict], object]) -> Path:
    """A minimal one-sample v1.0 table set (one LIDAR_TOP key frame, one car), changed by
    `mutate(tables)` before it is written."""
    root = case / "nuscenes"
    (root / "samples" / "LIDAR_TOP").mkdir(parents=True)
    shutil.copy(NUSCENES_SCAN, root / "samples" / "LIDAR_TOP" / NUSCENES_SCAN.name)
    pose = {"translation": [0.0, 0.0, 0.0], "rotation": [1.0, 0.0, 0.0, 0.0]}
    tables = {
        "sensor": [{"token": "lidar", "channel": "LIDAR_TOP"}],
        "calibrated_sensor": [{"token": "cs", "sensor_token": "lidar", **pose}],
        "ego_pose": [{"token": "ep", **pose}],
        "sample_data": [{"token": "sd", "sample_token": "s0", "ego_pose_token": "ep",
                         "calibrated_sensor_token": "cs", "is_key_frame": True,
                         "filename": f"samples/LIDAR_TOP/{NUSCENES_SCAN.name}"}],
        "sample": [{"token": "s0", "scene_token": "sc", "timestamp": 1}],
        "scene": [{"token": "sc", "name": "scene-0001"}],
        "category": [{"token": "c0", "name": "vehicle.car"}],
        "instance": [{"token": "i0", "category_token": "c0"}],
        "sample_annotation": [{"token": "a0", "sample_token": "s0", "instance_token": "i0",
                               "num_lidar_pts": 5, "translation": [10.0, 0.0, 0.0],
                               "size": [1.8, 4.2, 1.5], "rotation": [1, 0, 0, 0]}],
    }  # fmt: skip
    mutate(tables)
    (root / "v1.0-mini").mkdir()
    for name, rows in tables.items():
        (root / "v1.0-mini" / f"{name}.json").write_text(json.dumps(rows))
    return root


def _set(table: str, field: str, value, record: int = 0):
    """A mutation of nuscenes_tables: tables[table][record][field] = value (None: delete)."""

    def mutate(tables):
        if value is None:
            del tables[table][record][field]
        else:
            tables[table][record][field] = value

    return mutate


def _second_key_frame(tables):
    """Another sample whose LIDAR_TOP record names the same file (in sweeps/)."""
    first = tables["sample_data"][0]
    name = first["filename"].rsplit("/", 1)[1]
    tables["sample_data"].append(
        {**first, "token": "sd1", "sample_token": "s1", "filename": f"sweeps/LIDAR_TOP/{name}"}
    )
    tables["sample"].append({"token": "s1", "scene_token": "sc", "timestamp": 2})


NUSCENES_JSON_DAMAGE = {
    "filename-dotdot": (_set("sample_data", "filename", "samples/LIDAR_TOP/.."),
                        ("sample_data.json", "record 0", "frame id")),
    "filename-control": (_set("sample_data", "filename", "samples/LIDAR_TOP/a\x01b.pcd.bin"),
                         ("sample_data.json", "record 0", "control character")),
    "filename-number": (_set("sample_data", "filename", 7),
                        ("sample_data.json", "record 0", "'filename'", "string")),
    "duplicate-frame": (_second_key_frame,
                        ("sample_data.json", "record 1", "already used by record 0")),
    "record-not-object": (lambda t: t["sample_data"].__setitem__(0, [1, 2]),
                          ("sample_data.json", "record 0", "not a JSON object")),
    "sensor-without-token": (_set("sensor", "token", None),
                             ("sensor.json", "record 0", "no field 'token'")),
    "ego-translation-text": (_set("ego_pose", "translation", "abc"),
                             ("ego_pose.json", "record 0", "'translation'")),
    "ego-rotation-nan": (_set("ego_pose", "rotation", [float("nan"), 0, 0, 0]),
                         ("ego_pose.json", "record 0", "'rotation'", "finite")),
    "calib-zero-quaternion": (_set("calibrated_sensor", "rotation", [0, 0, 0, 0]),
                              ("calibrated_sensor.json", "record 0", "zero quaternion")),
    "timestamp-text": (_set("sample", "timestamp", "noon"),
                       ("sample.json", "record 0", "'timestamp'")),
    "category-without-name": (_set("category", "name", None),
                              ("category.json", "record 0", "no field 'name'")),
    "annotation-not-object": (lambda t: t["sample_annotation"].__setitem__(0, 5),
                              ("sample_annotation.json", "record 0", "not a JSON object")),
    "annotation-nan": (_set("sample_annotation", "translation", [float("nan"), 0, 0]),
                       ("sample_annotation.json", "NaN/inf")),
    "annotation-num-lidar-pts-2**40": (_set("sample_annotation", "num_lidar_pts", 2**40),
                                       ("sample_annotation.json", "num_lidar_pts")),
    "annotation-num-lidar-pts-text": (_set("sample_annotation", "num_lidar_pts", "many"),
                                      ("sample_annotation.json", "num_lidar_pts")),
    "annotation-size-missing": (_set("sample_annotation", "size", [1.8, 4.2]),
                                ("sample_annotation.json", "malformed annotation")),
}  # fmt: skip


@pytest.mark.skipif(NUSCENES_SCAN is None, reason="nuScenes fixture scan missing")
@pytest.mark.parametrize("how", list(NUSCENES_JSON_DAMAGE))
def test_import_nuscenes_tables_refuse_malformed_records(tmp_path, how):
    mutate, needles = NUSCENES_JSON_DAMAGE[how]
    root = nuscenes_tables(tmp_path, mutate)
    expect_refused(tmp_path, ["import", "nuscenes", root, "--out", out_of(tmp_path)], *needles)


def openpcdet_case(world: Path, case: Path, how: str) -> tuple[list, tuple[str, ...]]:
    root = case / "openpcdet"
    (root / "points").mkdir(parents=True)
    (root / "labels").mkdir()
    points = np.random.default_rng(0).normal(size=(50, 4)).astype(np.float32)
    points[:, 3] = np.abs(points[:, 3]) % 1.0  # intensities in [0, 1], the contract's
    np.save(root / "points" / "000000.npy", points)
    (root / "labels" / "000000.txt").write_text(
        "10 0 -1 4 1.8 1.5 0.1 Car\n12 5 -1 4 1.8 1.5 0 Car\n"
    )
    extra: list = []
    npy, label = root / "points" / "000000.npy", root / "labels" / "000000.txt"
    if how == "npy-strings":
        np.save(npy, np.array([["a", "b", "c", "d"]]))
        need: tuple = ("000000.npy", "numeric (n, >=4)")
    elif how == "npy-1d":
        np.save(npy, np.zeros(12, np.float32))
        need = ("000000.npy", "(n, >=4)")
    elif how == "npy-nan":
        points[7, 0] = np.nan
        np.save(npy, points)
        need = ("000000.npy", "point 7", "NaN/inf")
    elif how == "npy-truncated":
        npy.write_bytes(npy.read_bytes()[:100])
        need = ("000000.npy", "cannot read")
    elif how == "npy-pickle":
        np.save(npy, np.array([{"a": 1}], dtype=object), allow_pickle=True)
        need = ("000000.npy", "cannot read")
    elif how == "label-7-fields":
        label.write_text("10 0 -1 4 1.8 1.5 Car\n")
        need = ("000000.txt", "line 1", "7 fields")
    elif how == "label-nan":
        label.write_text("10 0 -1 4 1.8 1.5 0 Car\n10 nan -1 4 1.8 1.5 0 Car\n")
        need = ("000000.txt", "line 2", "'y'")
    elif how == "label-binary":
        label.write_bytes(b"10 0 -1 4 1.8 1.5 0 \xff\xfeCar\n")
        need = ("000000.txt", "not UTF-8")
    elif how == "label-negative":
        label.write_text("10 0 -1 4 -1.8 1.5 0 Car\n")
        need = ("000000.txt", "line 1", "negative size")
    elif how.startswith("split-"):
        frame_id = HOSTILE[how[6:]]
        frame_id = str(case / "abs") if frame_id == "ABS" else frame_id
        (root / "ImageSets").mkdir()
        (root / "ImageSets" / "val.txt").write_text(f"000000\n{frame_id}\n")
        extra = ["--split", "val"]
        need = ("val.txt", "line 2", "frame id")
    else:
        raise ValueError(how)
    return ["import", "openpcdet", root, "--sensor", "kitti", *extra, "--out", out_of(case)], need


OPENPCDET_DAMAGE = [
    "npy-strings",
    "npy-1d",
    "npy-nan",
    "npy-truncated",
    "npy-pickle",
    "label-7-fields",
    "label-nan",
    "label-binary",
    "label-negative",
    *(f"split-{name}" for name in HOSTILE if name != "nul"),
]


@pytest.mark.parametrize("how", OPENPCDET_DAMAGE)
def test_import_openpcdet_refuses_malformed_files(world, tmp_path, how):
    args, needles = openpcdet_case(world, tmp_path, how)
    expect_refused(tmp_path, args, *needles)


def test_export_openpcdet_refuses_a_split_name_outside_out(world, tmp_path):
    expect_refused(
        tmp_path,
        ["export", "openpcdet", world / "target", "--split", "../../../evil", "--out",
         out_of(tmp_path)],
        "ImageSets", "evil",
    )  # fmt: skip


def test_a_valid_box_table_still_passes_every_box_stage(world, tmp_path):
    """The control: the undamaged inputs of the cases above are accepted."""
    boxes = tmp_path / "boxes"
    boxes.mkdir()
    write_boxes(boxes, read_boxes(world / "target"))
    for stage in ("eval-pred", "view", "export-kitti", "export-openpcdet"):
        case = tmp_path / stage
        case.mkdir()
        result = invoke(*BOX_STAGES[stage](world, case, boxes))
        assert result.exit_code == 0, (stage, result.output)
