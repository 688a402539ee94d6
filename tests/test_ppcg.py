"""RC and CF on scanned synthetic scenes: geometry of the generated points, skips, determinism, CLI."""

from __future__ import annotations

from functools import lru_cache

import click
import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli.geometry import bev_iou, shrink_boxes
from dali_cli.library import point_models_from_frame, procedural_car, write_library
from dali_cli.ppcg.cf import CfParams, cf_frame
from dali_cli.ppcg.fitting import model_to_sensor, sensor_to_model
from dali_cli.ppcg.models import ModelBank
from dali_cli.ppcg.point_models import angular_threshold_rad
from dali_cli.ppcg.rc import RcParams, rc_frame
from dali_cli.raycast import Scene, cast, cast_into_box
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import BoxTable, FrameSet, read_boxes, write_boxes, write_frameset
from dali_cli.store.manifest import read_manifest
from dali_cli.world.cars import LABEL_SLACK_M

PROFILE = get_profile("kitti")
GROUND_Z = -PROFILE.mount_height_m
THETA = angular_threshold_rad(PROFILE.points_per_beam)


@lru_cache(maxsize=4)
def car(seed: int, lod: int = 2000):
    return procedural_car([123, seed], lod=lod)


def bank_of(*seeds: int) -> ModelBank:
    models = [car(s) for s in seeds]
    return ModelBank(
        "cad",
        [m.model_id for m in models],
        np.array([m.native_lwh for m in models]),
        meshes=[(m.vertices, m.faces) for m in models],
    )


def on_ground(x: float, y: float, lwh, yaw: float) -> np.ndarray:
    length, width, height = lwh
    return np.array([x, y, GROUND_Z + height / 2, length, width, height, yaw])


@lru_cache(maxsize=8)
def _scan(boxes_key: tuple, seeds: tuple) -> np.ndarray:
    """Points `(n, 4)` of a ground plane and car meshes placed in boxes, full KITTI pattern.
    Intensity = (index + 1) / n so every output point can be traced back to its source ray."""
    boxes = np.array(boxes_key).reshape(-1, 7)
    ground = (
        np.array(
            [[-90, -90, GROUND_Z], [90, -90, GROUND_Z], [90, 90, GROUND_Z], [-90, 90, GROUND_Z]],
            np.float32,
        ),
        np.array([[0, 1, 2], [0, 2, 3]], np.int32),
    )
    meshes = [ground] + [
        (model_to_sensor(car(seed).vertices, box).astype(np.float32), car(seed).faces)
        for box, seed in zip(boxes, seeds, strict=True)
    ]
    hits = cast(Scene(meshes), np.zeros(3), PROFILE.ray_pattern().directions, max_distance=80.0)
    xyz = hits.points[hits.hit]
    intensity = (np.arange(len(xyz)) + 1.0) / len(xyz)
    return np.concatenate([xyz, intensity[:, None]], axis=1).astype(np.float32)


def scan(boxes: np.ndarray, seeds) -> np.ndarray:
    return _scan(tuple(np.asarray(boxes, float).ravel().tolist()), tuple(seeds)).copy()


def distance_to_mesh(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Reference: distance `(m,)` from points `(m, 3)` to the nearest of triangles `(t, 3, 3)`
    among those whose plane projection of the point falls inside them (brute force, m x t)."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]  # (t, 3)
    normal = np.cross(b - a, c - a)
    area2 = np.linalg.norm(normal, axis=1)
    keep = area2 > 1e-12
    a, b, c, normal = a[keep], b[keep], c[keep], normal[keep] / area2[keep, None]
    offset = points[:, None, :] - a[None]  # (m, t, 3)
    height = np.einsum("mtk,tk->mt", offset, normal)
    foot = points[:, None, :] - height[..., None] * normal[None]  # (m, t, 3)

    def side(p, q):  # barycentric sign of the foot against edge p -> q
        return np.einsum("mtk,tk->mt", np.cross(q - p, foot - p[None]), normal)

    inside = (side(a, b) >= -1e-9) & (side(b, c) >= -1e-9) & (side(c, a) >= -1e-9)
    return np.where(inside, np.abs(height), np.inf).min(axis=1)


def rc_params(**overrides) -> RcParams:
    return RcParams(mount_height_m=PROFILE.mount_height_m, theta_rad=THETA, **overrides)


def source_of(out: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Index of each output point's source point, from its intensity code."""
    return np.rint(out[:, 3].astype(np.float64) * len(points)).astype(np.int64) - 1


# ------------------------------------------------------------------------------------------ RC


@pytest.mark.parametrize("slack", [(0.0, 0.0, 0.0), tuple(LABEL_SLACK_M)])
def test_rc_points_lie_on_the_fitted_mesh_and_on_their_rays(slack):
    """The model fills the pseudo box shrunk by the labels' slack (all of it with none)."""
    truth = np.array(
        [
            on_ground(14.0, 4.0, car(1).native_lwh, 0.6),
            on_ground(25.0, -6.0, car(2).native_lwh, -2.0),
        ]
    )
    points = scan(truth, (1, 2))
    pseudo = truth + [0.2, -0.1, 0.05, 0.3, 0.1, -0.05, 0.08]  # noisy pseudo boxes
    bank = bank_of(3)  # a different car than the one scanned
    params = rc_params(max_points=10**6, label_slack_m=slack)
    out, records = rc_frame("f", points, pseudo, bank, params)
    assert list(records.ppcg) == ["rc", "rc"]
    assert len(out) <= len(points) and (records.points_after <= records.points_before).all()
    source = source_of(out, points)
    moved = np.flatnonzero(np.any(out[:, :3] != points[source, :3], axis=1))
    assert len(moved) > 200
    # on the ray of the source point
    a, b = out[moved, :3].astype(np.float64), points[source[moved], :3].astype(np.float64)
    cosine = np.einsum("ij,ij->i", a, b) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    assert np.arccos(np.clip(cosine, -1, 1)).max() <= 1e-6
    # on the fitted mesh: raycast's own transformed-ray cast finds the same surface point
    model = car(3)
    for box in shrink_boxes(pseudo, slack):
        mine = moved[np.abs(sensor_to_model(a, box)).max(axis=1) <= 0.5 + 1e-6]
        assert len(mine) > 50
        reference = cast_into_box(model.bvh(), np.zeros(3), out[mine, :3].astype(np.float64), box)
        assert reference.hit.all()
        assert np.abs(reference.points - out[mine, :3]).max() <= 1e-3
        triangles = model_to_sensor(model.vertices[model.faces].reshape(-1, 3), box).reshape(
            -1, 3, 3
        )
        assert distance_to_mesh(out[mine[:150], :3].astype(np.float64), triangles).max() <= 1e-3
    # every other point is untouched and in order
    unchanged = np.setdiff1d(np.arange(len(out)), moved)
    np.testing.assert_array_equal(out[unchanged], points[source[unchanged]])
    assert (np.diff(source) > 0).all()


def fit_visible_faces(xyz: np.ndarray, pseudo: np.ndarray) -> np.ndarray:
    """A box `(1, 7)` of the pseudo box's size and heading fitted to points `(m, 3)`: its faces
    that the sensor sees touch the outermost points (how one fits a box to an L-shaped scan)."""
    local = sensor_to_model(xyz, pseudo) * pseudo[3:6]
    sensor = sensor_to_model(np.zeros((1, 3)), pseudo)[0]
    centre = np.zeros(3)
    for axis in (0, 1):
        half = pseudo[3 + axis] / 2
        visible_low = sensor[axis] < 0
        centre[axis] = local[:, axis].min() + half if visible_low else local[:, axis].max() - half
    x, y, _ = model_to_sensor((centre / pseudo[3:6])[None], pseudo)[0]
    return np.array([[x, y, pseudo[2], *pseudo[3:]]])


@pytest.mark.parametrize("view_deg", [35, 200])
def test_rc_points_agree_with_a_noisy_pseudo_box(view_deg):
    truth = on_ground(10.0, 3.0, car(1).native_lwh, np.radians(view_deg))
    points = scan(truth[None], (1,))
    pseudo = truth.copy()
    pseudo[3:6] *= [1.12, 1.08, 1.0]  # a pseudo box larger than the car
    out, records = rc_frame("f", points, pseudo[None], bank_of(2), rc_params(max_points=10**6))
    assert records.ppcg[0] == "rc"

    def car_points(frame: np.ndarray) -> np.ndarray:
        local = sensor_to_model(frame[:, :3].astype(np.float64), pseudo)
        inside = (np.abs(local) <= 0.5).all(axis=1) & (frame[:, 2] >= GROUND_Z + 0.1)
        return frame[inside, :3].astype(np.float64)

    raw_iou = bev_iou(fit_visible_faces(car_points(points), pseudo), pseudo[None])[0, 0]
    rc_iou = bev_iou(fit_visible_faces(car_points(out), pseudo), pseudo[None])[0, 0]
    # the model's ends bulge, so a face fit on its points stays a little inside the box
    assert rc_iou >= 0.85 and rc_iou > raw_iou + 0.05


def test_model_scale_is_applied():
    """A 3 m box gets a 3 m car: CF points of a side-on box span its length, not the model's."""
    truth = on_ground(10.0, 3.0, car(1).native_lwh, np.arctan2(3.0, 10.0) + np.pi / 2)
    points = scan(truth[None], (1,))
    bank = bank_of(2)
    assert bank.lwh[0, 0] > 4.0
    spans = []
    for length in (3.0, 4.5):
        box = truth.copy()
        box[3] = length
        params = CfParams(theta_rad=THETA, range_m=(12.0, 12.0))
        out, records = cf_frame("f", points, box[None], bank, PROFILE, params)
        assert records.ppcg[0] == "cf"
        new = out[len(out) - records.points_after[0] :, :3].astype(np.float64)
        along = sensor_to_model(new, box)[:, 0] * length
        assert np.abs(along).max() <= length / 2 + 1e-3
        spans.append(np.ptp(along))
    assert spans[0] > 0.9 * 3.0
    assert spans[1] / spans[0] == pytest.approx(1.5, abs=0.05)


def test_rc_skips_dense_and_sparse_boxes_keeps_ground_and_never_adds_points():
    truth = np.array(
        [
            on_ground(7.0, 0.5, car(1).native_lwh, 0.1),  # dense
            on_ground(30.0, 8.0, car(2).native_lwh, 1.0),  # sparse enough for RC
        ]
    )
    points = scan(truth, (1, 2))
    far_empty = on_ground(60.0, -40.0, (4.0, 1.8, 1.5), 0.0)  # no points at all
    sunk = truth.copy()
    sunk[:, 2] -= 0.3  # pseudo boxes sunk 30 cm into the road
    boxes = np.concatenate([sunk, far_empty[None]])
    out, records = rc_frame("f", points, boxes, bank_of(3), rc_params(max_points=300))
    assert list(records.reason) == ["dense", "ok", "too_few_points"]
    assert list(records.ppcg) == ["raw", "rc", "raw"]
    assert records.points_before[0] >= 300 and records.points_before[2] == 0
    assert records.ground_points[1] > 0  # the sunk box holds road points ...
    source = source_of(out, points)
    local = sensor_to_model(points[:, :3].astype(np.float64), boxes[1])
    ground_in_box = np.flatnonzero(
        (np.abs(local) <= 0.5).all(axis=1) & (points[:, 2] < GROUND_Z + 0.1)
    )
    assert len(ground_in_box) == records.ground_points[1]
    kept = np.isin(ground_in_box, source)
    assert kept.all()  # ... and they all stay, unmoved
    np.testing.assert_array_equal(out[np.isin(source, ground_in_box)], points[ground_in_box])
    assert len(out) <= len(points)


def test_rc_with_point_models_keeps_rays_and_uses_the_nearest_model_point():
    truth = np.array(
        [on_ground(9.0, 2.0, car(1).native_lwh, 2.2), on_ground(20.0, -5.0, car(2).native_lwh, 0.4)]
    )
    source_points = scan(truth, (1, 2))
    models = point_models_from_frame(source_points, truth, "src", min_points=300)
    assert len(models) == 2
    bank = ModelBank(
        "points", list(models.model_id), models.lwh, points=models.points, offsets=models.offsets,
        angles=models.view_angle_rad,
    )  # fmt: skip
    target = np.array([on_ground(18.0, 6.0, car(3).native_lwh, 2.9)])
    points = scan(target, (3,))
    out, records = rc_frame("t", points, target, bank, rc_params(max_points=10**6))
    assert records.ppcg[0] == "rc" and 0 < records.points_after[0] <= records.points_before[0]
    source = source_of(out, points)
    moved = np.flatnonzero(np.any(out[:, :3] != points[source, :3], axis=1))
    a, b = out[moved, :3].astype(np.float64), points[source[moved], :3].astype(np.float64)
    cosine = np.einsum("ij,ij->i", a, b) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    assert np.arccos(np.clip(cosine, -1, 1)).max() <= 1e-6
    # the model chosen is the one seen from the most similar direction
    assert records.model_id[0] == bank.model_ids[bank.select(target)[0]]


def test_cast_many_equals_one_cast_per_box():
    rng = np.random.default_rng(4)
    bank = bank_of(1, 2, 3)
    boxes = np.array(
        [on_ground(*rng.uniform(-30, 30, 2), (4.2, 1.8, 1.5), rng.uniform(-3, 3)) for _ in range(4)]
    )
    sizes = [50, 0, 120, 7]
    directions = np.concatenate(
        [
            box[:3] + rng.normal(size=(n, 3)) * [1.5, 0.7, 0.5]
            for box, n in zip(boxes, sizes, strict=True)
        ]
    )
    bounds = np.r_[0, np.cumsum(sizes)]
    models = np.array([2, 0, 1, 2])
    hit, xyz = bank.cast_many(models, boxes, directions, bounds, THETA)
    assert hit.any() and (~hit).any()
    for b in range(len(boxes)):
        one_hit, one_xyz = bank.cast(
            int(models[b]), boxes[b], directions[bounds[b] : bounds[b + 1]], THETA
        )
        np.testing.assert_array_equal(hit[bounds[b] : bounds[b + 1]], one_hit)
        np.testing.assert_allclose(xyz[bounds[b] : bounds[b + 1]], one_xyz, atol=1e-9)


# ------------------------------------------------------------------------------------------ CF


def full_pattern_hits(model, box: np.ndarray) -> int:
    """Reference: every ray of the pattern cast against the model in `box` (no window)."""
    directions = PROFILE.ray_pattern().directions.astype(np.float64)
    hits = cast_into_box(model.bvh(), np.zeros(3), directions, box)
    distance = np.where(hits.hit, hits.distance, np.inf)
    return int(((distance >= PROFILE.min_range_m) & (distance <= PROFILE.max_range_m)).sum())


def test_cf_points_stay_in_the_box_and_thin_out_with_range_as_the_pattern_predicts():
    box = on_ground(6.0, 0.0, (4.5, 1.8, 1.5), np.pi / 2)  # side-on, close
    points = scan(box[None], (1,))
    bank = bank_of(2)
    counts = []
    for range_m in (8.0, 16.0, 32.0):
        out, records = cf_frame(
            "f",
            points,
            box[None],
            bank,
            PROFILE,
            CfParams(theta_rad=THETA, range_m=(range_m, range_m), ground_margin_m=0.0),
        )
        new = out[len(out) - records.points_after[0] :, :3].astype(np.float64)
        local = sensor_to_model(new, box) * box[3:6]
        assert (np.abs(local) <= box[3:6] / 2 + 0.01).all()
        moved = shrink_boxes(box, LABEL_SLACK_M)[0]  # the model fills the body inside the box
        moved[:2] *= range_m / np.hypot(*box[:2])
        assert records.points_after[0] == full_pattern_hits(
            car(2), moved
        )  # the window loses no ray
        counts.append(records.points_after[0])
    assert counts[0] > counts[1] > counts[2] > 0
    # a solid angle shrinking as 1/r^2: doubling the range keeps roughly a quarter of the points
    assert 2.5 < counts[0] / counts[1] < 6 and 2.5 < counts[1] / counts[2] < 6


def test_cf_is_reproducible_per_box_and_draws_ranges_per_box():
    truth = np.array(
        [
            on_ground(12.0, 5.0, car(1).native_lwh, 0.3),
            on_ground(-15.0, -9.0, car(2).native_lwh, 2.0),
        ]
    )
    points = scan(truth, (1, 2))
    params = CfParams(theta_rad=THETA, range_m=(20.0, 50.0), seed=4)
    first, records = cf_frame("000007", points, truth, bank_of(3), PROFILE, params)
    again, _ = cf_frame("000007", points, truth, bank_of(3), PROFILE, params)
    np.testing.assert_array_equal(first, again)
    other, _ = cf_frame("000008", points, truth, bank_of(3), PROFILE, params)
    assert len(other) != len(first) or not np.array_equal(other, first)
    # reversing the box order changes which stream each box gets, but each box alone is the same
    alone, alone_records = cf_frame("000007", points, truth[:1], bank_of(3), PROFILE, params)
    assert alone_records.points_after[0] == records.points_after[0]


# ------------------------------------------------------------------------------------------ stage


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ppcg")
    frames, ids, boxes = [], [], []
    layouts = [
        [
            on_ground(14.0, 4.0, car(1).native_lwh, 0.6),
            on_ground(25.0, -6.0, car(2).native_lwh, -2.0),
        ],
        [],
        [on_ground(-20.0, 3.0, car(2).native_lwh, 1.2)],
    ]
    for index, layout in enumerate(layouts):
        layout = np.array(layout).reshape(-1, 7)
        points = scan(layout, (1, 2)[: len(layout)]) if len(layout) else scan(np.zeros((0, 7)), ())
        frames.append((f"{index:06d}", points))
        ids += [f"{index:06d}"] * len(layout)
        boxes.append(layout)
    write_frameset(root / "target", frames, sensor="kitti")
    table = BoxTable.from_arrays(ids, np.concatenate(boxes), label=["Car", "Car", "Van"])
    write_boxes(root / "target", table)
    library = root / "library"
    library.mkdir()
    point_models = point_models_from_frame(frames[0][1], boxes[0], frames[0][0], min_points=100)
    assert len(point_models) == 2
    write_library(library, [car(3), car(1)], point_models)
    return root


def test_stage_outputs_and_worker_independence(dataset):
    from stages.ppcg_cf import ppcg_cf
    from stages.ppcg_rc import ppcg_rc

    target, library = dataset / "target", dataset / "library"
    ppcg_rc(target, target, library, dataset / "rc1", max_points=10**5, progress=False)
    again = ppcg_rc(target, target, library, dataset / "rc1", max_points=10**5, progress=False)
    assert again.status == "skipped"
    dry = ppcg_rc(target, target, library, dataset / "rc9", dry_run=True, progress=False)
    assert dry.status == "dry-run" and not (dataset / "rc9").exists()
    boxes = read_boxes(dataset / "rc1")
    assert list(boxes["ppcg"]) == ["rc", "rc", "raw"]
    assert list(boxes["ppcg_reason"]) == ["ok", "ok", "label"]
    assert (boxes["points_after"][:2] > 0).all() and boxes["model_id"][0] in (
        car(3).model_id,
        car(1).model_id,
    )
    manifest = read_manifest(dataset / "rc1")
    counts = manifest["outputs"]["counts"]
    assert (
        counts["frames_without_boxes"] == 2
        and counts["boxes_rc"] == 2
        and counts["boxes_other_label"] == 1
    )
    assert len(manifest["per_frame_compute_seconds"]) == 3
    source, result = FrameSet(target), FrameSet(dataset / "rc1")
    np.testing.assert_array_equal(result.frame(1), source.frame(1))  # frames without boxes pass
    np.testing.assert_array_equal(result.frame(2), source.frame(2))  # only a Van there
    ppcg_cf(target, target, library, dataset / "cf1", seed=3, top_k=2, progress=False)
    ppcg_cf(target, target, library, dataset / "cf2", seed=3, top_k=2, workers=2, progress=False)
    assert (
        read_manifest(dataset / "cf1")["content_hash"]
        == read_manifest(dataset / "cf2")["content_hash"]
    )
    assert list(read_boxes(dataset / "cf1")["ppcg"]) == ["cf", "cf", "raw"]
    # point models from the same library
    ppcg_rc(
        target, target, library, dataset / "rcp", models="points", max_points=10**5, progress=False
    )
    points_table = read_boxes(dataset / "rcp")
    assert list(points_table["ppcg"]) == ["rc", "rc", "raw"]
    assert set(points_table["model_id"][:2]) <= {"000000#0", "000000#1"}
    assert read_manifest(dataset / "rcp")["params"]["models"] == "points"
    # the before/after figure for `dali report` (paper Fig. 9)
    from dali_cli.ppcg.figure import plot_ppcg_examples

    png = plot_ppcg_examples(
        dataset / "rc1", dataset / "cf1", dataset / "fig" / "ppcg.png", count=2
    )
    assert png is not None and png.stat().st_size > 10_000


@pytest.mark.parametrize("mode", ["rc", "cf"])
def test_implausible_boxes_are_refused_naming_row_frame_and_field(dataset, tmp_path, mode):
    """A pseudo box 1,000 km long once went through ppcg-rc and was re-cast; the same table is
    refused as pretrain refuses it (one plausibility rule), nothing written."""
    from dali_cli.store.artifacts import ArtifactError
    from stages.ppcg_cf import ppcg_cf
    from stages.ppcg_rc import ppcg_rc

    stage = {"rc": ppcg_rc, "cf": ppcg_cf}[mode]
    target, library = dataset / "target", dataset / "library"
    given = read_boxes(target)
    options = {"max_points": 10**5} if mode == "rc" else {"seed": 3}
    for field, value, needle in ((3, 1e6, "'l' = 1e+06 m"), (0, 1e6, "centre (x, y, z)")):
        bad = given.boxes[:1].copy()
        bad[:, field] = value
        noisy = BoxTable.concat([BoxTable.from_arrays(["000000"], bad, label="Car"), given])
        boxes = tmp_path / f"boxes{field}"
        boxes.mkdir()
        write_boxes(boxes, noisy)
        with pytest.raises(ArtifactError) as error:
            stage(target, boxes, library, tmp_path / "noisy", progress=False, **options)
        assert "row 0" in str(error.value) and "000000" in str(error.value)
        assert needle in str(error.value)
        assert not (tmp_path / "noisy").exists()


def test_cli_errors_name_the_file_frame_and_field(dataset, tmp_path):
    from dali_cli.cli import main

    target, library = dataset / "target", dataset / "library"
    bad = tmp_path / "bad"
    bad.mkdir()
    write_boxes(bad, BoxTable.from_arrays(["000009"], np.array([[10, 0, -1, 4, 2, 1.5, 0]])))
    runner = CliRunner()
    args = ["--data", str(target), "--library", str(library)]
    result = runner.invoke(
        main, ["ppcg-rc", *args, "--boxes", str(bad), "--out", str(tmp_path / "o")]
    )
    assert result.exit_code == 1 and "000009" in result.output and "boxes.parquet" in result.output
    write_boxes(bad, BoxTable.from_arrays(["000000"], np.array([[10, 0, -1, 0.0, 2, 1.5, 0]])))
    result = runner.invoke(
        main, ["ppcg-cf", *args, "--boxes", str(bad), "--out", str(tmp_path / "o")]
    )
    assert result.exit_code == 1 and "'l'" in result.output and "000000" in result.output
    result = runner.invoke(
        main,
        [
            "ppcg-cf",
            *args,
            "--boxes",
            str(target),
            "--range-m",
            "50:20",
            "--out",
            str(tmp_path / "o"),
        ],
    )
    assert result.exit_code == 2 and "--range-m" in result.output
    meshes_only = tmp_path / "meshes_only"
    meshes_only.mkdir()
    write_library(meshes_only, [car(3)])
    result = runner.invoke(
        main,
        ["ppcg-rc", "--data", str(target), "--library", str(meshes_only), "--boxes", str(target)]
        + ["--models", "points", "--out", str(tmp_path / "o")],
    )
    assert result.exit_code == 1 and "no point models" in result.output
    assert not (tmp_path / "o").exists()
    from dali_cli.commands.kinds import DISTANCE_RANGE

    with pytest.raises(click.BadParameter):
        DISTANCE_RANGE.convert("20-50", None, None)


def test_cf_with_the_calibrated_waymo_top_pattern_loses_no_ray():
    """CF-PPCG on sensors.toml's waymo_top (non-uniform calibrated beams): the angular window
    keeps every ray of the full pattern that hits the moved model."""
    profile = get_profile("waymo_top")
    box = on_ground(6.0, 0.0, (4.5, 1.8, 1.5), np.pi / 2)
    box[2] = -profile.mount_height_m + box[5] / 2
    points = scan(box[None], (1,))
    params = CfParams(
        theta_rad=angular_threshold_rad(profile.points_per_beam),
        range_m=(20.0, 20.0),
        ground_margin_m=0.0,
    )
    out, records = cf_frame("f", points, box[None], bank_of(2), profile, params)
    new = out[len(out) - records.points_after[0] :, :3].astype(np.float64)
    assert (np.abs(sensor_to_model(new, box) * box[3:6]) <= box[3:6] / 2 + 0.01).all()
    moved = shrink_boxes(box, params.label_slack_m)[0]
    moved[:2] *= 20.0 / np.hypot(*box[:2])
    directions = profile.ray_pattern().directions.astype(np.float64)
    hits = cast_into_box(car(2).bvh(), np.zeros(3), directions, moved)
    distance = np.where(hits.hit, hits.distance, np.inf)
    expected = int(((distance >= profile.min_range_m) & (distance <= profile.max_range_m)).sum())
    assert records.points_after[0] == expected > 50
