"""The heading metrics of `dali eval` (AOS, APH, AOE, backwards share) on hand-computed cases: a
perfect detector, every box turned by pi, by pi/2, and half of the boxes turned around."""

from __future__ import annotations

import numpy as np
import pytest

from dali_cli.evaluation.evaluate import evaluate, format_table
from dali_cli.evaluation.heading import heading_summary, heading_weight
from dali_cli.geometry import wrap_angle
from dali_cli.store.artifacts import BoxTable

SQUARE_CAR = (2.0, 2.0, 1.5)  # turned by pi/2 it overlaps as before: the heading alone changes


def cars(count: int, yaw: np.ndarray | float = 0.0) -> np.ndarray:
    """`count` separated square cars `(count, 7)` along +x with headings `yaw`."""
    x = 5.0 + 6.0 * np.arange(count)
    yaws = np.broadcast_to(np.asarray(yaw, float), (count,))
    return np.c_[
        x, np.full(count, 3.0), np.full(count, -0.9), np.tile(SQUARE_CAR, (count, 1)), yaws
    ]


def table(boxes, score=None) -> BoxTable:
    return BoxTable.from_arrays(["000000"] * len(boxes), boxes, score=score, label="Car")


def scored(turn: np.ndarray | float, count: int = 50, positions: int = 40) -> dict:
    truth = cars(count, yaw=np.linspace(-3.0, 3.0, count))
    pred = truth.copy()
    pred[:, 6] = wrap_angle(pred[:, 6] + turn)
    score = np.linspace(0.9, 0.5, count)
    return evaluate(table(pred, score), table(truth), recall_positions=positions)["Car"]


@pytest.mark.parametrize("positions", [40, 400])
def test_a_perfect_detector_scores_its_ap_in_every_heading_metric(positions):
    metrics = scored(0.0, positions=positions)
    assert metrics["bev"]["all"] == pytest.approx(100.0)
    assert metrics["aos"]["all"] == pytest.approx(100.0)
    assert metrics["aph"]["all"] == pytest.approx(100.0)
    heading = metrics["heading"]["all"]
    assert heading == {"tp": 50, "aoe_rad": 0.0, "backwards": 0, "backwards_share": 0.0}


@pytest.mark.parametrize("positions", [40, 400])
def test_boxes_turned_around_keep_their_ap_and_score_zero_heading(positions):
    metrics = scored(np.pi, positions=positions)
    assert metrics["bev"]["all"] == pytest.approx(100.0)
    assert metrics["aos"]["all"] == pytest.approx(0.0, abs=1e-9)
    assert metrics["aph"]["all"] == pytest.approx(0.0, abs=1e-9)
    heading = metrics["heading"]["all"]
    assert heading["backwards"] == 50 and heading["aoe_rad"] == pytest.approx(np.pi, abs=1e-4)


def test_a_quarter_turn_halves_both():
    metrics = scored(np.pi / 2)
    assert metrics["bev"]["all"] == pytest.approx(100.0)
    assert metrics["aos"]["all"] == pytest.approx(50.0)
    assert metrics["aph"]["all"] == pytest.approx(50.0)
    assert metrics["heading"]["all"]["aoe_rad"] == pytest.approx(np.pi / 2, abs=1e-4)
    assert metrics["heading"]["all"]["backwards"] == 0  # exactly 90 deg is not backwards


def test_aos_and_aph_weigh_small_errors_differently():
    """At 60 deg: AOS (1 + cos)/2 = 0.75, APH 1 - 1/3 = 0.667 of AP."""
    metrics = scored(np.pi / 3)
    assert metrics["aos"]["all"] == pytest.approx(75.0)
    assert metrics["aph"]["all"] == pytest.approx(100 * 2 / 3)


def test_half_turned_around_with_false_positives():
    """The weighted precision counts false positives in its denominator like AP does: the first
    25 by score right, the last 25 backwards, then 10 false positives below every true one."""
    count = 50
    truth = cars(count, yaw=0.3)
    pred = truth.copy()
    pred[25:, 6] = wrap_angle(pred[25:, 6] + np.pi)
    far = cars(10) + [0, 40.0, 0, 0, 0, 0, 0]  # nowhere near a car
    boxes = np.r_[pred, far]
    score = np.r_[np.linspace(0.9, 0.5, count), np.full(10, 0.1)]
    metrics = evaluate(table(boxes, score), table(truth), recall_positions=400)["Car"]
    assert metrics["bev"]["all"] == pytest.approx(100.0)  # the false positives rank last
    # at j true positives the heading-weighted precision is min(j, 25) / j; at recall r = x / 50
    # the envelope takes its best over j >= x (max-interpolation from the right)
    x = np.arange(1, 401) / 400 * 50
    envelope = [max(min(j, 25) / j for j in range(int(np.ceil(v - 1e-9)), 51)) for v in x]
    assert metrics["aos"]["all"] == pytest.approx(100 * np.mean(envelope), abs=1e-6)
    assert metrics["aph"]["all"] == pytest.approx(metrics["aos"]["all"])
    assert metrics["heading"]["all"]["backwards_share"] == 0.5
    assert "APH" in format_table({"Car": metrics})


def test_heading_weights_at_hand_computed_angles():
    delta = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2, 3 * np.pi])
    assert np.allclose(heading_weight(delta, 0.0, "aos"), [1, 0.5, 0, 0.5, 0])
    assert np.allclose(heading_weight(delta, 0.0, "aph"), [1, 0.5, 0, 0.5, 0])
    assert heading_summary(np.zeros(0), np.zeros(0))["aoe_rad"] is None
    with pytest.raises(ValueError, match="unknown heading metric"):
        heading_weight(delta, 0.0, "nope")
