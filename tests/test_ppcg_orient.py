"""Orienting boxes by their fitted car model (dali_cli.ppcg.orient, `--orient-models`): a box
turned round is turned back when its model fits its points better that way, RC and CF then
give the points of the rightly headed box, and the stages record it."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from test_ppcg import PROFILE, bank_of, car, dataset, on_ground, rc_params, scan  # noqa: F401

from dali_cli.geometry import point_box_indices, wrap_angle
from dali_cli.ppcg.cf import CfParams, cf_frame
from dali_cli.ppcg.frame import car_points, ground_heights
from dali_cli.ppcg.orient import MIN_POINTS, flips, heading_costs, turned
from dali_cli.ppcg.rc import rc_frame
from dali_cli.store.artifacts import FrameSet, read_boxes, write_boxes
from dali_cli.store.manifest import read_manifest
from dali_cli.world.cars import LABEL_SLACK_M

SCENES = [
    [on_ground(14.0, 4.0, car(1).native_lwh, 0.6), on_ground(25.0, -6.0, car(2).native_lwh, -2.0)],
    [on_ground(9.0, -3.0, car(2).native_lwh, 1.9), on_ground(32.0, 8.0, car(1).native_lwh, 3.0)],
]


def members_of(points: np.ndarray, boxes: np.ndarray) -> list:
    return car_points(points, boxes, ground_heights(boxes, PROFILE.mount_height_m, 0.1))[0]


@pytest.mark.parametrize("scene", range(len(SCENES)))
@pytest.mark.parametrize("model_seed", [None, 3])
def test_the_model_tells_a_box_turned_round(scene, model_seed):
    """With the scanned cars' own meshes and with another car's: the right heading is kept, a
    box turned round is flagged."""
    truth = np.array(SCENES[scene])
    points = scan(truth, (1, 2) if scene == 0 else (2, 1))
    seeds = (1, 2) if scene == 0 else (2, 1)
    bank = bank_of(*seeds) if model_seed is None else bank_of(model_seed)
    models = np.arange(len(truth)) if model_seed is None else np.zeros(len(truth), np.int64)
    members = members_of(points, truth)
    assert not flips(bank, models, truth, points, members).any()
    reversed_boxes = turned(truth, np.ones(len(truth), bool))
    assert flips(bank, models, reversed_boxes, points, members).all()
    costs = heading_costs(bank, models, truth, points, members)
    assert (costs[:, 0] < costs[:, 1]).all() and (costs >= 0).all()


def test_boxes_with_too_few_points_keep_their_heading():
    truth = np.array(SCENES[0])
    points = scan(truth, (1, 2))
    members = members_of(points, truth)
    few = [members[0][: MIN_POINTS - 1], members[1]]
    reversed_boxes = turned(truth, np.ones(2, bool))
    costs = heading_costs(bank_of(1, 2), np.arange(2), reversed_boxes, points, few)
    assert np.isnan(costs[0]).all() and np.isfinite(costs[1]).all()
    assert list(flips(bank_of(1, 2), np.arange(2), reversed_boxes, points, few)) == [False, True]


def test_rc_and_cf_of_reversed_boxes_equal_those_of_the_right_ones_when_oriented():
    truth = np.array(SCENES[0])
    points = scan(truth, (1, 2))
    reversed_boxes = turned(truth, np.ones(2, bool))
    bank = bank_of(3)
    for run, params in (
        (lambda b, p: rc_frame("f", points, b, bank, p), rc_params(max_points=10**6)),
        (lambda b, p: cf_frame("f", points, b, bank, PROFILE, p), CfParams(theta_rad=0.01)),
    ):
        right, right_records = run(truth, params)
        oriented, records = run(reversed_boxes, type(params)(**{**vars(params), "orient": True}))
        wrong, wrong_records = run(reversed_boxes, params)
        assert records.flipped.all() and not right_records.flipped.any()
        assert not wrong_records.flipped.any()
        assert oriented.shape == right.shape
        np.testing.assert_allclose(oriented, right, atol=1e-4)
        assert wrong.shape != right.shape or np.abs(wrong - right).max() > 0.05


def test_the_stages_turn_the_boxes_and_record_it(dataset, tmp_path):  # noqa: F811
    from dali_cli.cli import main
    from stages.ppcg_cf import ppcg_cf
    from stages.ppcg_rc import ppcg_rc

    target, library = dataset / "target", dataset / "library"
    given = read_boxes(target)
    reversed_table = given.with_columns(yaw=wrap_angle(given.boxes[:, 6] + np.pi))
    (tmp_path / "boxes").mkdir()
    write_boxes(tmp_path / "boxes", reversed_table)
    boxes = tmp_path / "boxes"
    ppcg_rc(target, boxes, library, tmp_path / "rc", max_points=10**5, orient_models=False,
            progress=False)  # fmt: skip
    ppcg_rc(target, boxes, library, tmp_path / "rco", max_points=10**5, progress=False)
    plain, oriented = read_boxes(tmp_path / "rc"), read_boxes(tmp_path / "rco")
    assert "heading_flipped" not in plain.columns
    assert "orient" not in read_manifest(tmp_path / "rc")["params"]
    assert read_manifest(tmp_path / "rco")["params"]["orient"] is True  # mesh models: on
    named = ppcg_rc(target, boxes, library, tmp_path / "rco", max_points=10**5,
                    orient_models=True, progress=False)  # fmt: skip
    assert named.status == "skipped"  # the default, named: the same artifact
    cars = np.asarray(oriented["ppcg"]) == "rc"  # the Van passes through untouched
    assert list(oriented["heading_flipped"]) == list(cars)
    turn = wrap_angle(oriented.boxes[:, 6] - given.boxes[:, 6])
    np.testing.assert_allclose(turn[cars], 0.0, atol=1e-9)
    np.testing.assert_allclose(np.abs(turn[~cars]), np.pi, atol=1e-9)
    # CF with two workers (shards) equals CF in this process, turned boxes included
    ppcg_cf(target, boxes, library, tmp_path / "cf1", seed=3, orient_models=True, progress=False)
    ppcg_cf(target, boxes, library, tmp_path / "cf2", seed=3, orient_models=True, workers=2,
            progress=False)  # fmt: skip
    one, two = read_manifest(tmp_path / "cf1"), read_manifest(tmp_path / "cf2")
    assert one["content_hash"] == two["content_hash"]
    assert list(read_boxes(tmp_path / "cf2")["heading_flipped"]) == list(cars)
    for index in range(3):
        np.testing.assert_array_equal(
            FrameSet(tmp_path / "cf1").frame(index), FrameSet(tmp_path / "cf2").frame(index)
        )
    result = CliRunner().invoke(
        main,
        ["ppcg-rc", "--data", str(target), "--boxes", str(boxes), "--library", str(library),
         "--models", "points", "--orient-models", "--no-progress", "--out", str(tmp_path / "p")],
    )  # fmt: skip
    assert result.exit_code == 2 and "orient" in result.output and "cad" in result.output
    assert not (tmp_path / "p").exists()
    # by default point models are not oriented: no error
    result = CliRunner().invoke(
        main,
        ["ppcg-rc", "--data", str(target), "--boxes", str(boxes), "--library", str(library),
         "--models", "points", "--no-progress", "--out", str(tmp_path / "p")],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "orient" not in read_manifest(tmp_path / "p")["params"]


def test_orienting_needs_meshes():
    truth = np.array(SCENES[0])
    points = scan(truth, (1, 2))
    points_bank = type(bank_of(1))(
        "points", ["a"], np.array([[4.0, 1.8, 1.5]]), points=np.zeros((5, 4), np.float32),
        offsets=np.array([0, 5]), angles=np.zeros(1),
    )  # fmt: skip
    with pytest.raises(ValueError, match="mesh"):
        flips(points_bank, np.zeros(2, np.int64), truth, points, members_of(points, truth))


# ------------------------------------------------------------------------------ point margin


def raw_points_beside(out: np.ndarray, boxes: np.ndarray, margin_m: float) -> int:
    """Points of `out` above the ground in a box grown by `margin_m` but not in the box itself
    (1 cm of slack: model hits lie on the box's faces): real car points the model did not
    replace."""
    grown = boxes.copy()
    grown[:, 3:6] += 2 * margin_m
    above = out[:, 2] > -PROFILE.mount_height_m + 0.15
    inside = np.zeros(len(out), bool)
    for box in boxes:
        inside |= point_box_indices(out[:, :3], box[None], margin_m=0.01) == 0
    beside = np.zeros(len(out), bool)
    for box in grown:
        beside |= point_box_indices(out[:, :3], box[None]) == 0
    return int(np.count_nonzero(beside & ~inside & above))


@pytest.mark.parametrize("mode", ["rc", "cf"])
def test_a_point_margin_leaves_no_raw_car_points_beside_a_small_box(mode):
    """A pseudo box 0.3 m short and 0.2 m narrow (the car's faces outside it): by default the
    points outside stay as raw points beside the model; with --point-margin-m 0.3 every one is
    re-cast (RC: moved onto the model or dropped) or replaced (CF)."""
    truth = np.array(SCENES[0])
    points = scan(truth, (1, 2))
    small = truth.copy()
    small[:, 3] -= 0.3
    small[:, 4] -= 0.2
    bank = bank_of(3)
    if mode == "rc":

        def run(margin):
            return rc_frame("f", points, small, bank, rc_params(max_points=10**6,
                            point_margin_m=margin))[0]  # fmt: skip
    else:

        def run(margin):
            params = CfParams(theta_rad=0.01, point_margin_m=margin)
            return cf_frame("f", points, small, bank, PROFILE, params)[0]

    assert raw_points_beside(points, small, 0.3) > 100  # the scan: faces outside the box
    assert raw_points_beside(run(0.0), small, 0.3) > 100
    assert raw_points_beside(run(0.3), small, 0.3) == 0
    far = np.hypot(points[:, 0] - 14.0, points[:, 1] - 4.0) > 6  # away from both cars
    far &= np.hypot(points[:, 0] - 25.0, points[:, 1] + 6.0) > 6
    assert len(run(0.3)) >= np.count_nonzero(far)  # the rest of the frame is kept


def test_the_point_margin_is_recorded_only_when_used(dataset, tmp_path):  # noqa: F811
    from stages.ppcg_rc import ppcg_rc

    target, library = dataset / "target", dataset / "library"
    ppcg_rc(target, target, library, tmp_path / "a", point_margin_m=0.0, progress=False)
    ppcg_rc(target, target, library, tmp_path / "b", progress=False)  # the default: 0.3 m
    assert "point_margin_m" not in read_manifest(tmp_path / "a")["params"]
    assert read_manifest(tmp_path / "b")["params"]["point_margin_m"] == 0.3
    from dali_cli.runtime.errors import ParameterError

    with pytest.raises(ParameterError, match="point_margin_m"):
        ppcg_rc(target, target, library, tmp_path / "c", point_margin_m=-1.0, progress=False)
    assert not (tmp_path / "c").exists()


def test_the_label_slack_is_recorded_and_checked(dataset, tmp_path):  # noqa: F811
    from dali_cli.runtime.errors import ParameterError
    from stages.ppcg_cf import ppcg_cf

    target, library = dataset / "target", dataset / "library"
    ppcg_cf(target, target, library, tmp_path / "a", progress=False)
    recorded = read_manifest(tmp_path / "a")["params"]["label_slack_m"]
    np.testing.assert_allclose(recorded, LABEL_SLACK_M)  # the synthetic world's labels
    for bad in ((0.6, 0.0, 0.0), (0.0, -0.01, 0.0)):
        with pytest.raises(ParameterError, match="label_slack_m"):
            ppcg_cf(target, target, library, tmp_path / "c", label_slack_m=bad, progress=False)
        assert not (tmp_path / "c").exists()


def test_the_report_figure_takes_rc_and_cf_boxes_turned_round_as_one_table():
    """RC turns only the boxes it re-casts, CF every car: their output tables differ by half
    turns, and `dali report`'s PPCG figure must still see one box table (otherwise `make demo`'s
    report fails), but not boxes moved, resized or turned by anything else."""
    from dali_cli.ppcg.figure import same_boxes

    rc = np.array(SCENES[0])
    cf = rc.copy()
    cf[0, 6] = wrap_angle(cf[0, 6] + np.pi)
    assert same_boxes(rc, cf) and same_boxes(rc, rc)
    for column, change in ((6, 0.1), (0, 0.01), (3, 0.01)):
        other = cf.copy()
        other[1, column] += change
        assert not same_boxes(rc, other)
    assert not same_boxes(rc, cf[:1])
