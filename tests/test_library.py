"""Model library: procedural cars, CAD loading, point models, the library artifact and its command."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.library import (
    LibraryError,
    axis_rotation,
    load_cad_directory,
    load_cad_file,
    point_models_from_frame,
    procedural_car,
    proportions_problem,
    read_library,
    write_library,
)
from dali_cli.procedural import KINDS
from dali_cli.store.artifacts import BoxTable, write_boxes, write_frameset


@pytest.mark.parametrize("kind", KINDS)
def test_procedural_cars_are_closed_unit_box_meshes_with_kind_sizes(kind):
    model = procedural_car(7, kind=kind, lod=5000)
    mesh = trimesh.Trimesh(model.vertices, model.faces, process=False)
    assert mesh.is_watertight
    np.testing.assert_allclose(model.vertices.min(axis=0), -0.5, atol=1e-6)
    np.testing.assert_allclose(model.vertices.max(axis=0), 0.5, atol=1e-6)
    length, width, height = model.native_lwh
    assert 3.4 < length < 6.5 and 1.5 < width < 2.3 and 1.2 < height < 2.3
    assert model.kind == kind and model.faces.dtype == np.int32


@pytest.mark.parametrize("kind", KINDS)
def test_procedural_car_ends_bulge_without_folding(kind):
    from dali_cli import procedural

    stations, around, _ = procedural._resolution(5000)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        shape = procedural.sample_shape(rng, kind)
        vertices, _ = procedural._body(shape, stations, around, rng)
        grid = vertices[: stations * around].reshape(stations, around, 3)
        # every line along the body runs from the front bumper to the rear one without folding
        assert (np.diff(grid[:, :, 0], axis=0) < 0).all()
        centres = vertices[stations * around :]  # the end caps' middles: front, rear
        for end, centre, sign in ((grid[0], centres[0], 1.0), (grid[-1], centres[1], -1.0)):
            trail = sign * (centre[0] - end[:, 0])  # (A,) how far each rim point lies behind
            outer = np.abs(end[:, 1]) > 0.8 * np.abs(end[:, 1]).max()
            # the middle of each end leads; its rim trails, its corners by most of the least bow
            assert trail.min() > 0.02
            assert trail[outer].min() > 0.8 * procedural.END_BOW_M[0] * 0.72**2
        assert shape.end_bow <= procedural.END_BOW_REACH_M  # the bow fades out before it folds


def test_procedural_kinds_have_kind_specific_heights():
    heights = {
        k: np.mean([procedural_car(s, kind=k, lod=2000).native_lwh[2] for s in range(4)])
        for k in KINDS
    }
    assert heights["sedan"] < heights["suv"] < heights["van"]


@pytest.mark.parametrize("lod", [5000, 20000, 70000])
def test_procedural_lod_sets_the_triangle_count(lod):
    model = procedural_car(3, lod=lod)
    assert 0.85 * lod <= model.num_triangles <= 1.1 * lod


def test_procedural_is_deterministic_per_seed():
    first, again, other = (
        procedural_car(11, lod=3000),
        procedural_car(11, lod=3000),
        procedural_car(12, lod=3000),
    )
    np.testing.assert_array_equal(first.vertices, again.vertices)
    np.testing.assert_array_equal(first.native_lwh, again.native_lwh)
    assert first.vertices.shape != other.vertices.shape or not np.array_equal(
        first.vertices, other.vertices
    )
    with pytest.raises(ValueError, match="unknown car kind"):
        procedural_car(1, kind="tank")


def _write_obj_y_up(path, length=4.0, width=1.8, height=1.5, material=True):
    """A box car exported y-up with -z forward (a common DCC convention) and a missing material."""
    box = trimesh.creation.box(extents=[length, width, height])
    # dali (x fwd, y left, z up) -> file (x right = -y_dali, y up = z_dali, z back = -x_dali)
    file_vertices = np.stack([-box.vertices[:, 1], box.vertices[:, 2], -box.vertices[:, 0]], axis=1)
    lines = ["mtllib missing_materials.mtl", "usemtl CarPaint"] if material else []
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in file_vertices]
    lines += ["vt 0 0", "usemtl AlsoMissing"] if material else []
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in box.faces]
    path.write_text("\n".join(lines) + "\n")


def test_cad_obj_with_missing_materials_and_y_up_loads_with_axis_options(tmp_path):
    path = tmp_path / "car.obj"
    _write_obj_y_up(path)
    model = load_cad_file(path, up="y", forward="-z")
    np.testing.assert_allclose(model.native_lwh, [4.0, 1.8, 1.5], rtol=1e-6)
    wrong = load_cad_file(path)  # default z up, x forward reads the axes wrongly
    assert not np.allclose(wrong.native_lwh, [4.0, 1.8, 1.5])


def test_cad_directory_rejects_degenerate_and_empty_files_naming_them(tmp_path):
    _write_obj_y_up(tmp_path / "good.obj")
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n")
    with pytest.raises(LibraryError, match="flat.obj"):
        load_cad_directory(tmp_path, up="y", forward="-z")
    models, skipped = load_cad_directory(tmp_path, up="y", forward="-z", skip_bad=True)
    assert [m.model_id for m in models] == ["good"] and len(skipped) == 1
    (tmp_path / "empty.stl").write_text("")
    models, skipped = load_cad_directory(tmp_path, up="y", forward="-z", skip_bad=True)
    assert len(models) == 1 and len(skipped) == 2
    kept, _ = load_cad_directory(
        tmp_path, up="y", forward="-z", length_range=(3.5, 4.5), skip_bad=True
    )
    assert len(kept) == 1
    with pytest.raises(LibraryError, match="no usable models"):
        load_cad_directory(tmp_path, up="y", forward="-z", length_range=(4.5, 8.0), skip_bad=True)
    with pytest.raises(LibraryError, match="not found"):
        load_cad_directory(tmp_path / "nope")
    with pytest.raises(LibraryError, match="--up"):
        load_cad_file(tmp_path / "good.obj", up="q")


def _write_obj_in_axes(path, up, forward, lwh=(4.0, 1.8, 1.5)):
    """A box car written in a file whose axes are `up` and `forward` (like "y", "-z")."""
    box = trimesh.creation.box(extents=lwh)
    rotation = axis_rotation(up, forward)  # rows: dali x, y, z in file coordinates
    file_vertices = box.vertices @ rotation  # dali -> file
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in file_vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in box.faces]
    path.write_text("\n".join(lines) + "\n")


AXES = ["x", "-x", "y", "-y", "z", "-z"]
FILE_CONVENTIONS = [(u, f) for u in AXES for f in AXES if u.lstrip("-") != f.lstrip("-")]


@pytest.mark.parametrize("up, forward", FILE_CONVENTIONS)
def test_odd_proportions_name_the_axes_that_make_a_car(tmp_path, up, forward):
    # any of the 24 file conventions read with the defaults (z up, x forward): either right, or
    # refused with --forward/--up that give l > w > h when followed
    path = tmp_path / "car.obj"
    _write_obj_in_axes(path, up, forward)
    model = load_cad_file(path)
    problem = proportions_problem(model.native_lwh)
    if up.lstrip("-") == "z" and forward.lstrip("-") == "x":
        assert problem is None
        return
    assert problem is not None and "contradict a car" in problem
    suggested = re.search(r"--forward (\S+) --up (\S+) would", problem)
    assert suggested, problem
    fixed = load_cad_file(path, up=suggested[2], forward=suggested[1])
    np.testing.assert_allclose(fixed.native_lwh, [4.0, 1.8, 1.5], rtol=1e-6)
    assert proportions_problem(fixed.native_lwh, suggested[2], suggested[1]) is None
    with pytest.raises(LibraryError, match=r"car\.obj: extents .* --forward"):
        load_cad_directory(tmp_path)


def test_mis_oriented_cad_is_refused_skipped_or_kept_on_request(tmp_path):
    # a model with its length along z and y up, read with the default --forward x --up z
    cad = tmp_path / "cad"
    cad.mkdir()
    _write_obj_y_up(cad / "y_up.obj")
    _write_obj_in_axes(cad / "z_up.obj", "z", "x")
    with pytest.raises(LibraryError, match=r"y_up\.obj: .*--forward z --up y would"):
        load_cad_directory(cad)
    models, skipped = load_cad_directory(cad, skip_bad=True)
    assert [m.model_id for m in models] == ["z_up"] and "y_up.obj" in skipped[0]
    models, skipped = load_cad_directory(cad, keep_odd_proportions=True)
    assert len(models) == 2 and skipped == []
    # the user's signs are kept where an axis keeps its role
    assert "--forward -z --up x would" in proportions_problem([4.0, 1.5, 1.8], "-y", "-z")
    assert "--forward x --up -y would" in proportions_problem([1.8, 4.0, 1.5], "-y", "-z")
    cube = proportions_problem([2.0, 2.0, 1.0])
    assert "no axis mapping does, two extents are equal" in cube

    runner = CliRunner()
    out = tmp_path / "lib"
    result = runner.invoke(main, ["library", "build", "--cad", str(cad), "--out", str(out)])
    assert result.exit_code == 1 and "y_up.obj" in result.output
    assert "--forward z --up y" in result.output and "--force" in result.output
    assert not out.exists()
    result = runner.invoke(
        main, ["library", "build", "--cad", str(cad), "--out", str(out), "--force"]
    )
    assert result.exit_code == 0, result.output
    assert "WARNING" in result.output and "y_up.obj" in result.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["outputs"]["counts"]["cad_odd_proportions_kept"] == 1
    assert any("kept (--force)" in note and "y_up.obj" in note for note in manifest["notes"])
    assert len(read_library(out).meshes) == 2


def _car_points(box, count, rng):
    """Points inside `box` (7,) in the sensor frame, (count, 4) float32."""
    local = rng.uniform(-0.5, 0.5, (count, 3)) * box[3:6]
    c, s = np.cos(box[6]), np.sin(box[6])
    xyz = np.stack(
        [c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1], local[:, 2]], 1
    )
    return np.concatenate([xyz + box[:3], rng.uniform(0, 1, (count, 1))], 1).astype(
        np.float32
    ), local


def test_point_models_are_box_normalized_with_viewing_angle():
    rng = np.random.default_rng(0)
    boxes = np.array(
        [
            [10.0, 0.0, -0.9, 4.0, 1.8, 1.5, 0.0],
            [0.0, 12.0, -0.9, 4.5, 1.9, 1.6, 0.7],
            [30, 30, -1, 4, 2, 1.5, 0],
        ]
    )
    first, local_first = _car_points(boxes[0], 400, rng)
    second, local_second = _car_points(boxes[1], 350, rng)
    sparse, _ = _car_points(boxes[2], 20, rng)
    clutter = np.concatenate(
        [rng.uniform(-50, 50, (500, 3)) * [1, 1, 0] + [0, 0, -5], np.zeros((500, 1))], 1
    )
    points = np.concatenate([first, clutter.astype(np.float32), second, sparse])
    models = point_models_from_frame(points, boxes, "f0", "kitti", min_points=300)
    assert len(models) == 2 and list(models.num_points) == [400, 350]
    np.testing.assert_allclose(
        models.model_points(0)[:, :3], local_first / boxes[0, 3:6], atol=1e-5
    )
    np.testing.assert_allclose(
        models.model_points(1)[:, :3], local_second / boxes[1, 3:6], atol=1e-5
    )
    assert np.all(np.abs(models.points[:, :3]) <= 0.5 + 1e-5)
    # box 0 at +x facing +x sees the sensor behind it; box 1 at +y, yaw 0.7: sensor at -90 - 40 deg
    np.testing.assert_allclose(models.view_angle_rad[0], -np.pi, atol=1e-9)
    np.testing.assert_allclose(models.view_angle_rad[1], -np.pi / 2 - 0.7, atol=1e-9)
    np.testing.assert_allclose(models.lwh, boxes[:2, 3:6])


def test_library_round_trip_and_build_command(tmp_path):
    rng = np.random.default_rng(1)
    box = np.array([8.0, 3.0, -0.9, 4.0, 1.8, 1.5, 0.3])
    points, _ = _car_points(box, 320, rng)
    data = tmp_path / "data"
    data.mkdir()
    write_frameset(data, [("000", points), ("001", points[:10])], sensor="kitti")
    write_boxes(data, BoxTable.from_arrays(["000", "001"], np.stack([box, box])))
    (tmp_path / "cad" / "sub").mkdir(parents=True)
    _write_obj_y_up(tmp_path / "cad" / "sub" / "car.obj")

    runner = CliRunner()
    out = tmp_path / "lib"
    build = ["library", "build", "--cad", tmp_path / "cad", "--up", "y", "--forward", "-z",
             "--procedural", "2", "--seed", "4", "--lod", "2000", "--points", data, "--out", out]  # fmt: skip
    result = runner.invoke(main, [str(a) for a in build])
    assert result.exit_code == 0, result.output
    library = read_library(out)
    assert library.mesh_ids == ["sub/car", "proc-s4-00000", "proc-s4-00001"]
    np.testing.assert_allclose(library.mesh_lwh[0], [4.0, 1.8, 1.5], rtol=1e-6)
    assert len(library.point_models) == 1 and library.point_models.num_points[0] == 320
    again = procedural_car([4, 1], lod=2000)
    np.testing.assert_array_equal(library.meshes[2].vertices, again.vertices)
    np.testing.assert_array_equal(library.meshes[2].faces, again.faces)
    shown = runner.invoke(main, ["library", "show", str(out)])
    assert shown.exit_code == 0 and "3 meshes, 1 point models" in shown.output
    rerun = runner.invoke(main, [str(a) for a in build])
    assert "up to date" in rerun.output

    # write_library / read_library directly
    direct = tmp_path / "direct"
    direct.mkdir()
    write_library(direct, library.meshes[:1], library.point_models)
    back = read_library(direct)
    np.testing.assert_array_equal(back.meshes[0].vertices, library.meshes[0].vertices)
    np.testing.assert_array_equal(back.point_models.points, library.point_models.points)


def test_build_command_errors(tmp_path):
    runner = CliRunner()
    result = runner.invoke(main, ["library", "build", "--out", str(tmp_path / "x")])
    assert result.exit_code == 2 and "at least one of" in result.output
    result = runner.invoke(
        main, ["library", "build", "--cad", str(tmp_path / "none"), "--out", str(tmp_path / "x")]
    )
    assert result.exit_code == 2 and "none" in result.output
    (tmp_path / "cad").mkdir()
    (tmp_path / "cad" / "broken.ply").write_text("ply\nnot really\n")
    result = runner.invoke(
        main, ["library", "build", "--cad", str(tmp_path / "cad"), "--out", str(tmp_path / "x")]
    )
    assert result.exit_code == 1 and "broken.ply" in result.output
    assert not (tmp_path / "x").exists()
    with pytest.raises(LibraryError, match="missing"):
        read_library(tmp_path)


def test_cad_formats_glb_scene_ply_and_stl_load_as_one_normalized_mesh(tmp_path):
    body = trimesh.creation.box(extents=[4.2, 1.8, 1.0])
    body.apply_translation([0.0, 0.0, 0.7])
    cabin = trimesh.creation.box(extents=[2.0, 1.6, 0.6])
    cabin.apply_translation([-0.3, 0.0, 1.5])
    scene = trimesh.Scene([body, cabin])
    (tmp_path / "car.glb").write_bytes(scene.export(file_type="glb"))
    merged = trimesh.util.concatenate([body, cabin])
    merged.export(tmp_path / "car_ply.ply")
    merged.export(tmp_path / "car_stl.stl")
    models, skipped = load_cad_directory(tmp_path)
    assert skipped == [] and sorted(m.model_id for m in models) == ["car", "car_ply", "car_stl"]
    for model in models:
        np.testing.assert_allclose(model.native_lwh, [4.2, 1.8, 1.6], rtol=1e-5)
        np.testing.assert_allclose(model.vertices.min(axis=0), -0.5, atol=1e-6)
        np.testing.assert_allclose(model.vertices.max(axis=0), 0.5, atol=1e-6)
        assert len(model.faces) == 24


@pytest.mark.parametrize(
    "array", ["meshes/vertices", "meshes/faces", "meshes/face_offsets", "points/points"]
)
def test_a_missing_library_chunk_is_an_error_not_zeros(tmp_path, array):
    """Zarr reads a missing chunk as zeros (a flattened car, or offsets that still add up):
    the reader must refuse it and name the array."""
    rng = np.random.default_rng(0)
    box = np.array([10.0, 0.0, 0.0, 4.0, 1.8, 1.5, 0.3])
    points, _ = _car_points(box, 400, rng)
    models = point_models_from_frame(points, box[None], "f0", "kitti", min_points=300)
    directory = tmp_path / "lib"
    write_library(directory, [procedural_car(0, lod=1000)], models)
    read_library(directory)  # intact: reads
    chunk = directory / "library.zarr" / array / "c"
    for path in [p for p in chunk.rglob("*") if p.is_file()]:
        path.unlink()
    with pytest.raises(LibraryError, match=rf"{array}: 1 of 1 chunks missing"):
        read_library(directory)
