"""`ppcg-rc / ppcg-cf --occlusion`: the fitted model hides the scene behind it."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from test_ppcg import PROFILE, bank_of, car, dataset, on_ground, rc_params, scan  # noqa: F401

from dali_cli.ppcg.cf import CfParams, cf_frame
from dali_cli.ppcg.fitting import sensor_to_model
from dali_cli.ppcg.occlusion import GAP_M
from dali_cli.ppcg.rc import rc_frame
from dali_cli.raycast import cast_into_box
from dali_cli.store.artifacts import read_boxes
from dali_cli.store.manifest import read_manifest

TRUTH = np.array(
    [on_ground(14.0, 4.0, car(1).native_lwh, 0.6), on_ground(25.0, -6.0, car(2).native_lwh, -2.0)]
)


def behind_models(points: np.ndarray, boxes: np.ndarray, seed: int) -> int:
    """Reference, independent of dali_cli.ppcg.occlusion: points `(n, >=3)` whose ray from the
    sensor meets the mesh car(seed) fitted into any of `boxes` at least GAP_M before the point
    (raycast's own transformed-ray cast, every point against every box)."""
    xyz = points[:, :3].astype(np.float64)
    reach = np.linalg.norm(xyz, axis=1)
    behind = np.zeros(len(xyz), bool)
    for box in boxes:
        hits = cast_into_box(car(seed).bvh(), np.zeros(3), xyz, box)
        distance = np.linalg.norm(np.where(hits.hit[:, None], hits.points, 0.0), axis=1)
        behind |= hits.hit & (distance <= reach - GAP_M - 1e-4)
    return int(behind.sum())


def shifted(boxes: np.ndarray, along_m: float) -> np.ndarray:
    """Boxes moved along their heading (a pseudo box that is not where the car is)."""
    out = boxes.copy()
    out[:, 0] += along_m * np.cos(boxes[:, 6])
    out[:, 1] += along_m * np.sin(boxes[:, 6])
    return out


def run(mode: str, points: np.ndarray, boxes: np.ndarray, occlusion: bool):
    bank = bank_of(3)  # another car than the scanned ones: every box gets car(3)
    if mode == "rc":
        params = rc_params(max_points=10**6, point_margin_m=0.3, occlusion=occlusion)
        return rc_frame("f", points, boxes, bank, params)
    params = CfParams(theta_rad=0.01, point_margin_m=0.3, occlusion=occlusion)
    return cf_frame("f", points, boxes, bank, PROFILE, params)


@pytest.mark.parametrize("mode", ["rc", "cf"])
def test_no_scene_shows_through_a_model_car(mode):
    """Pseudo boxes 0.7 m off along the car: without occlusion ground and background points lie
    behind the model cars in the output; with it none does, and the rest of the frame stays."""
    points = scan(TRUTH, (1, 2))
    pseudo = shifted(TRUTH, 0.7)
    plain, plain_records = run(mode, points, pseudo, occlusion=False)
    out, records = run(mode, points, pseudo, occlusion=True)
    assert list(records.ppcg) == [mode, mode]
    # the frame's own points (CF's, appended last, may lie behind: its scan comes from farther
    # out, where the model shows parts hidden from the sensor's place)
    plain_scene, scene = (
        (plain[: len(plain) - plain_records.points_after.sum()],
         out[: len(out) - records.points_after.sum()]) if mode == "cf" else (plain, out)
    )  # fmt: skip
    assert behind_models(plain_scene, pseudo, 3) > 20
    assert (plain_records.hidden == 0).all()
    assert behind_models(scene, pseudo, 3) == 0
    assert records.hidden.sum() >= behind_models(plain_scene, pseudo, 3)  # each one was counted
    far = np.ones(len(points), bool)  # points in no car's direction are untouched
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    for box in pseudo:
        half_angle = np.arctan2(np.hypot(box[3], box[4]) / 2 + 0.5, np.hypot(box[0], box[1]))
        off = np.abs(np.angle(np.exp(1j * (azimuth - np.arctan2(box[1], box[0])))))
        far &= off > half_angle
    kept = {tuple(row) for row in out[:, :3].round(5).tolist()}
    assert all(tuple(row) in kept for row in points[far, :3].round(5).tolist())


def test_rc_moves_hidden_points_onto_the_model_along_their_rays():
    """RC never adds points; a hidden point keeps its ray and lands on the model's surface, with
    the box's car intensity; the counts add up."""
    points = scan(TRUTH, (1, 2))
    points[:, 3] = 0.9  # every raw point
    pseudo = shifted(TRUTH, 0.7)
    plain, _ = run("rc", points, pseudo, occlusion=False)
    out, records = run("rc", points, pseudo, occlusion=True)
    assert len(out) <= len(plain) <= len(points)
    moved = ~np.isin(out[:, :3].round(5).view([("", out.dtype)] * 3).ravel(),
                     plain[:, :3].round(5).view([("", plain.dtype)] * 3).ravel())  # fmt: skip
    assert moved.sum() > 0 and moved.sum() <= records.hidden.sum()
    xyz = out[moved, :3].astype(np.float64)
    on_a_model = np.zeros(len(xyz), bool)
    for box in pseudo:
        inside = np.abs(sensor_to_model(xyz, box)).max(axis=1) <= 0.5 + 1e-6
        hits = cast_into_box(car(3).bvh(), np.zeros(3), xyz[inside], box)
        assert hits.hit.all()  # on its own ray: the ray's first hit on the model is the point
        assert np.abs(hits.points - xyz[inside]).max() <= 1e-3
        on_a_model |= inside
    assert on_a_model.all()


def test_a_model_where_the_car_is_hides_little():
    """The scanned cars' own meshes in their true boxes: the scene behind them was never seen,
    so next to nothing is hidden (only rays grazing the mesh at float32 precision)."""
    points = scan(TRUTH, (1, 2))
    for seed, box in zip((1, 2), TRUTH, strict=True):
        params = rc_params(max_points=10**6, point_margin_m=0.3, occlusion=True)
        _, records = rc_frame("f", points, box[None], bank_of(seed), params)
        assert records.ppcg[0] == "rc" and records.hidden[0] <= 3
    _, records = run("rc", points, shifted(TRUTH, 0.7), occlusion=True)
    assert (records.hidden > 20).all()


def test_the_stages_record_occlusion_only_when_on(dataset, tmp_path):  # noqa: F811
    from dali_cli.cli import main

    target, library = dataset / "target", dataset / "library"
    for mode in ("rc", "cf"):
        common = ["--target", str(target), "--boxes", str(target), "--library", str(library),
                  "--no-progress"]  # fmt: skip
        plain = CliRunner().invoke(main, [f"ppcg-{mode}", *common, "--out", str(tmp_path / mode)])
        assert plain.exit_code == 0, plain.output
        occluded = tmp_path / f"{mode}-occ"
        result = CliRunner().invoke(main, [f"ppcg-{mode}", *common, "--occlusion", "--out",
                                           str(occluded)])  # fmt: skip
        assert result.exit_code == 0, result.output
        assert "occlusion" not in read_manifest(tmp_path / mode)["params"]
        assert "points_hidden" not in read_boxes(tmp_path / mode).extra_columns
        manifest = read_manifest(occluded)
        assert manifest["params"]["occlusion"] is True
        hidden = np.asarray(read_boxes(occluded)["points_hidden"])
        assert manifest["outputs"]["counts"]["points_hidden"] == int(hidden.sum())
        assert read_manifest(tmp_path / mode)["outputs"]["counts"]["points_hidden"] == 0
