"""PTSN: scale parsing, E_pred, bracket/grid search against stub detectors with known size laws,
and the `dali ptsn-sweep` stage end to end (stub detector, tiny frame sets)."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from dali_cli import ptsn
from dali_cli.cli import main
from dali_cli.store.artifacts import write_frameset

SOURCE_LWH = np.array([4.66, 2.08, 1.73])
KITTI_LWH = np.array([3.89, 1.62, 1.53])


class LawDetector:
    """Stub detector: in the scaled cloud it sees `boxes_for(points)` cars of size law(s) · s, so
    after de-scaling the sizes follow `law(s)` exactly. Frames with no points give no boxes."""

    def __init__(self, law, score=0.9, max_scale=None):
        self.law = law
        self.score = score
        self.max_scale = max_scale
        self.calls: list[tuple[float, int]] = []

    def predict(self, points_list, scale=1.0, mount_height_m=None):
        self.calls.append((scale, len(points_list)))
        results = []
        for points in points_list:
            count = 0 if len(points) == 0 else 1 + int(points[0, 3] * 10) % 3
            if self.max_scale is not None and scale > self.max_scale:
                count = 0
            boxes = np.zeros((count, 7))
            boxes[:, 0] = 10.0 + 5.0 * np.arange(count)
            boxes[:, 3:6] = self.law(scale)
            results.append((boxes, np.full(count, self.score, np.float32)))
        return results


def inverse_law(size):
    return lambda s: np.asarray(size) / s


def make_frames(count, seed=0, empty=()):
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(count):
        points = rng.uniform(-20, 20, size=(0 if i in empty else 50, 4)).astype(np.float32)
        if len(points):
            points[0, 3] = (i % 7) / 10.0  # the stub's box count
        frames.append(points)
    return frames


def run_search(detector, frames, e_est, **options):
    cache = ptsn.DetectionCache(detector, frames, score_min=0.3)
    indices = np.arange(len(frames))
    subsample = ptsn.subsample_for_bracket(indices, 0.25, 4, seed=0)
    result = ptsn.find_scale(
        cache,
        options.pop("scale_range", ptsn.ScaleRange(0.8, 1.4, 0.01)),
        e_est,
        indices,
        subsample=subsample,
        **options,
    )
    return result, cache


# ---------------------------------------------------------------------------------------------
# parsing


@pytest.mark.parametrize(
    "text, expected",
    [
        ("0.8:1.4", (0.8, 1.4, 0.01)),
        ("0.8:1.4:0.02", (0.8, 1.4, 0.02)),
        (" 0.5:2:0.5", (0.5, 2, 0.5)),
    ],
)
def test_parse_scale_range(text, expected):
    parsed = ptsn.parse_scale_range(text)
    assert (parsed.low, parsed.high, parsed.step) == pytest.approx(expected)
    grid = parsed.grid()
    assert grid[0] == pytest.approx(expected[0]) and grid[-1] == pytest.approx(expected[1])
    assert np.allclose(np.diff(grid), expected[2])


@pytest.mark.parametrize(
    "text", ["1.4:0.8", "0:1", "a:b", "1:1", "0.8", "0.8:1.4:0", "0.8:1.4:1", "-1:2"]
)
def test_parse_scale_range_rejects(text):
    with pytest.raises(ValueError):
        ptsn.parse_scale_range(text)


def test_grid_keeps_the_upper_bound_off_step():
    grid = ptsn.ScaleRange(0.8, 1.0, 0.03).grid()
    assert grid[-1] == pytest.approx(1.0) and np.all(np.diff(grid) > 0)


# ---------------------------------------------------------------------------------------------
# E_pred and the criterion


def test_per_frame_and_pooled_means_differ_as_defined():
    rng = np.random.default_rng(1)
    sizes = [rng.uniform(1, 5, (n, 3)) for n in (1, 4, 0, 9)]
    per_frame = ptsn.expected_prediction(sizes, "per-frame")
    pooled = ptsn.expected_prediction(sizes, "pooled")
    frame_means = np.stack([s.mean(axis=0) for s in sizes if len(s)])
    assert np.allclose(per_frame.mean_lwh, frame_means.mean(axis=0))
    assert np.allclose(pooled.mean_lwh, np.concatenate(sizes).mean(axis=0))
    assert not np.allclose(per_frame.mean_lwh, pooled.mean_lwh)
    assert (per_frame.frames, per_frame.frames_with_boxes, per_frame.boxes) == (4, 3, 14)


def test_no_boxes_gives_undefined_e_pred():
    stats = ptsn.expected_prediction([np.zeros((0, 3))] * 3)
    assert stats.boxes == 0 and np.isnan(stats.volume)
    assert np.isnan(ptsn.criterion(stats.mean_lwh, KITTI_LWH))


@pytest.mark.parametrize("match", ["volume", "lwh"])
def test_criterion_decreases_with_scale_and_vanishes_at_target(match):
    scales = np.linspace(0.7, 1.6, 50)
    values = [ptsn.criterion(SOURCE_LWH / s, KITTI_LWH, match) for s in scales]
    assert np.all(np.diff(values) < 0)
    assert ptsn.criterion(KITTI_LWH, KITTI_LWH, match) == pytest.approx(0.0, abs=1e-12)


def test_decreasing_fit_and_monotone_check():
    values = np.array([3.0, 2.0, 2.5, 1.0, 1.2, 0.0])
    fitted = ptsn.decreasing_fit(values)
    assert np.all(np.diff(fitted) <= 0) and fitted.sum() == pytest.approx(values.sum())
    scales = np.arange(6.0)
    assert not ptsn.is_monotone(scales, values, noise=0.1)
    assert ptsn.is_monotone(scales, values, noise=0.5)


def test_crossing_interpolates_and_clips():
    scales = np.array([1.0, 1.1, 1.2])
    assert ptsn.crossing(scales, np.array([2.0, 1.0, -1.0])) == (pytest.approx(1.15), None)
    assert ptsn.crossing(scales, np.array([-1.0, -2.0, -3.0])) == (1.0, "low")
    assert ptsn.crossing(scales, np.array([3.0, 2.0, 1.0])) == (1.2, "high")


# ---------------------------------------------------------------------------------------------
# search with stub detectors


@pytest.mark.parametrize("search", ["bracket", "grid"])
@pytest.mark.parametrize("mean", ["per-frame", "pooled"])
def test_known_size_law_gives_the_analytic_scale(search, mean):
    frames = make_frames(40)
    result, cache = run_search(
        LawDetector(inverse_law(SOURCE_LWH)), frames, KITTI_LWH, search=search, mean=mean
    )
    analytic = (np.prod(SOURCE_LWH) / np.prod(KITTI_LWH)) ** (1 / 3)
    assert result.scale == pytest.approx(analytic, abs=2e-3)
    assert result.clipped is None and result.fallback is None and result.monotone
    assert np.prod(result.mean_lwh) == pytest.approx(np.prod(KITTI_LWH), rel=1e-3)
    assert cache.frame_passes == sum(count for _, count in cache.detector.calls)


def test_lwh_match_finds_the_least_squares_scale():
    frames = make_frames(20)
    result, _ = run_search(
        LawDetector(inverse_law(SOURCE_LWH)), frames, KITTI_LWH, search="grid", match="lwh"
    )
    scales = np.linspace(0.8, 1.4, 60001)
    residual = ((SOURCE_LWH[None] / scales[:, None] - KITTI_LWH) ** 2).sum(axis=1)
    assert result.scale == pytest.approx(scales[np.argmin(residual)], abs=2e-3)


def test_bracket_needs_a_quarter_of_the_grid_passes_and_agrees():
    frames = make_frames(80)
    law = LawDetector(inverse_law(SOURCE_LWH))
    grid_result, grid_cache = run_search(law, frames, KITTI_LWH, search="grid")
    bracket_result, bracket_cache = run_search(law, frames, KITTI_LWH, search="bracket")
    assert abs(bracket_result.scale - grid_result.scale) <= 0.01
    assert bracket_cache.frame_passes * 4 <= grid_cache.frame_passes
    assert grid_cache.frame_passes == len(ptsn.ScaleRange(0.8, 1.4, 0.01).grid()) * len(frames)


def test_cache_never_repeats_a_frame_scale_pass():
    frames = make_frames(30)
    detector = LawDetector(inverse_law(SOURCE_LWH))
    _, cache = run_search(detector, frames, KITTI_LWH, search="bracket")
    runs = []
    for scale, _ in detector.calls:
        runs.append(round(scale, 9))
    per_scale = {s: sum(n for c, n in detector.calls if round(c, 9) == s) for s in set(runs)}
    assert all(count <= len(frames) for count in per_scale.values())
    before = cache.frame_passes
    cache.detections(runs[0], range(len(frames)))
    cache.detections(runs[0], range(len(frames)))
    assert cache.frame_passes - before == len(frames) - per_scale[runs[0]]


@pytest.mark.parametrize("search", ["bracket", "grid"])
def test_target_outside_the_range_is_clipped_loudly(search):
    frames = make_frames(16)
    big_target = SOURCE_LWH / 1.6  # needs s = 1.6 > 1.4
    result, _ = run_search(LawDetector(inverse_law(SOURCE_LWH)), frames, big_target, search=search)
    assert result.clipped == "high" and result.scale == pytest.approx(1.4)
    assert any("outside the swept range" in w for w in result.warnings)
    small_target = SOURCE_LWH / 0.7
    result, _ = run_search(
        LawDetector(inverse_law(SOURCE_LWH)), frames, small_target, search=search
    )
    assert result.clipped == "low" and result.scale == pytest.approx(0.8)


def test_no_detections_is_an_error_that_says_what_to_do():
    frames = make_frames(10)
    for search in ("bracket", "grid"):
        with pytest.raises(ptsn.NoDetectionsError, match="no detections") as caught:
            run_search(
                LawDetector(inverse_law(SOURCE_LWH), score=0.1), frames, KITTI_LWH, search=search
            )
        assert "more frames or epochs" in str(caught.value) and "--score-min" in str(caught.value)


@pytest.mark.parametrize("search", ["bracket", "grid"])
def test_no_detections_can_fall_back_to_no_scaling(search):
    # an undertrained model (every score below --score-min): ŝ = 1, said loudly, no E_pred
    frames = make_frames(10)
    detector = LawDetector(inverse_law(SOURCE_LWH), score=0.1)
    result, cache = run_search(detector, frames, KITTI_LWH, search=search, no_detections="identity")
    assert result.scale == 1.0 and result.fallback == "no-detections"
    assert result.monotone is None and result.clipped is None
    assert np.isnan(result.mean_lwh).all()
    assert len(result.warnings) == 1 and "ŝ = 1" in result.warnings[0]
    assert "--score-min" in result.warnings[0] and "--no-detections error" in result.warnings[0]
    assert result.evaluations and all(e.stats.boxes == 0 for e in result.evaluations)
    assert cache.frame_passes > 0
    # the same detector above the threshold gives a real scale: the fallback is only for nothing
    found, _ = run_search(
        LawDetector(inverse_law(SOURCE_LWH), score=0.31),
        frames,
        KITTI_LWH,
        search=search,
        no_detections="identity",
    )
    assert found.fallback is None and found.scale != 1.0


def test_no_detections_at_large_scales_is_worked_around():
    frames = make_frames(20)
    detector = LawDetector(inverse_law(SOURCE_LWH), max_scale=1.3)
    result, _ = run_search(detector, frames, KITTI_LWH, search="bracket")
    analytic = (np.prod(SOURCE_LWH) / np.prod(KITTI_LWH)) ** (1 / 3)
    assert result.scale == pytest.approx(analytic, abs=2e-3)


def bumpy_law(s):
    """1/s, except a 60 % rise between s = 1.0 and 1.2 (a non-monotone detector)."""
    factor = np.where(s <= 1.0, 1 / s, np.where(s <= 1.2, 1 + 3 * (s - 1.0), 1.6 * 1.2 / s))
    return SOURCE_LWH * factor


def test_non_monotone_curve_falls_back_to_a_local_grid():
    frames = make_frames(20)
    target = SOURCE_LWH * 1.25  # crossed three times: s = 0.8, 1.083, 1.536 (outside)
    result, _ = run_search(LawDetector(bumpy_law), frames, target, search="bracket")
    assert result.fallback == "local-grid" and not result.monotone
    assert any("not monotone" in w for w in result.warnings)
    # the non-increasing fit of the evaluated curve crosses E_est where ŝ is
    scales = np.array([e.scale for e in result.evaluations if e.subset == "all"])
    assert len(scales) >= 5
    grid_result, _ = run_search(LawDetector(bumpy_law), frames, target, search="grid")
    assert not grid_result.monotone and any("not monotone" in w for w in grid_result.warnings)


def test_select_frames_is_seeded_and_sized():
    a = ptsn.select_frames(100, 10, None, seed=3)
    b = ptsn.select_frames(100, 10, None, seed=3)
    c = ptsn.select_frames(100, None, 0.25, seed=4)
    assert np.array_equal(a, b) and len(a) == 10 and len(set(a.tolist())) == 10
    assert len(c) == 25 and np.all(np.diff(c) > 0)
    assert np.array_equal(ptsn.select_frames(5, None, None, 0), np.arange(5))


@pytest.mark.parametrize("count, frames", [(514, 64), (108, 64), (65, 64), (1000, 7)])
def test_select_frames_draws_one_frame_from_each_of_equal_runs(count, frames):
    picked = ptsn.select_frames(count, frames, None, seed=0)
    runs = np.arange(frames + 1) * count // frames  # the runs' edges
    assert len(picked) == frames and np.all(np.diff(picked) > 0)
    assert np.array_equal(np.searchsorted(runs, picked, side="right") - 1, np.arange(frames))
    if count >= 2 * frames:  # every run has a choice: another seed draws another sample
        assert not np.array_equal(picked, ptsn.select_frames(count, frames, None, seed=1))


def test_select_frames_caps_a_large_target_by_default():
    assert len(ptsn.select_frames(514, None, None, 0)) == ptsn.FRAME_CAP
    assert np.array_equal(ptsn.select_frames(514, None, 1.0, 0), np.arange(514))


def test_ros_expected_size():
    assert np.allclose(ptsn.ros_expected_size(SOURCE_LWH, 0.875), SOURCE_LWH * 0.875)


# ---------------------------------------------------------------------------------------------
# the stage and the CLI


@pytest.fixture
def sweep_setup(tmp_path, monkeypatch):
    """A tiny kitti target frame set (one empty frame), a model dir, and the stub as detector."""
    target = tmp_path / "target"
    target.mkdir()
    frames = make_frames(12, empty=(3,))
    write_frameset(target, [(f"{i:04d}", p) for i, p in enumerate(frames)], sensor="kitti")
    model = tmp_path / "model"
    model.mkdir()
    (model / "model.json").write_text(json.dumps({"config": {"sensor": "waymo"}}))
    detector = LawDetector(inverse_law(SOURCE_LWH))
    import stages.ptsn_sweep

    monkeypatch.setattr(stages.ptsn_sweep, "load_detector", lambda model_dir: detector)
    return tmp_path, target, model


def invoke(*arguments):
    return CliRunner().invoke(main, ["ptsn-sweep", *map(str, arguments)])


@pytest.mark.parametrize("spec", ["1.4:0.8", "0:1", "a:b"])
def test_cli_bad_scales_are_usage_errors(spec, sweep_setup):
    tmp_path, target, model = sweep_setup
    result = invoke("--model", model, "--data", target, "--out", tmp_path / "o", "--scales", spec)
    assert result.exit_code == 2, result.output
    assert "--scales" in result.output
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("spec, step", [("0.8:1.4", 0.01), ("0.8:1.4:0.02", 0.02)])
def test_cli_sweep_writes_scale_and_curve(spec, step, sweep_setup):
    tmp_path, target, model = sweep_setup
    out = tmp_path / f"ptsn{step}"
    arguments = [
        "--model",
        model,
        "--data",
        target,
        "--out",
        out,
        "--scales",
        spec,
        "--no-progress",
    ]
    result = invoke(*arguments, "--plot")
    assert result.exit_code == 0, result.output
    document = json.loads((out / "scale.json").read_text())
    analytic = (np.prod(SOURCE_LWH) / np.prod(KITTI_LWH)) ** (1 / 3)
    assert document["scale"] == pytest.approx(analytic, abs=2e-3)
    assert document["scale_range"] == pytest.approx([0.8, 1.4, step])
    assert document["E_est"] == pytest.approx(KITTI_LWH.tolist())  # sn from the kitti profile
    assert document["frames"]["skipped_no_points"] == 1 and document["frames"]["used"] == 11
    assert document["bias_lwh"] == pytest.approx(
        (SOURCE_LWH / analytic - KITTI_LWH).tolist(), abs=2e-3
    )
    sweep = pq.read_table(out / "sweep.parquet").to_pylist()
    assert len(sweep) == document["passes"]
    assert sum(row["frame_passes"] for row in sweep) == document["detector_frames"]
    assert {
        "scale",
        "frames",
        "boxes",
        "mean_l",
        "mean_w",
        "mean_h",
        "mean_volume",
        "seconds",
    } <= set(sweep[0])
    assert (out / "sweep.png").stat().st_size > 1000
    assert json.loads((out / "manifest.json").read_text())["stage"] == "ptsn_sweep"
    rerun = invoke(*arguments, "--plot")
    assert rerun.exit_code == 0 and "up to date" in rerun.output


def test_cli_expected_size_options(sweep_setup):
    tmp_path, target, model = sweep_setup
    base = [
        "--model",
        model,
        "--data",
        target,
        "--no-progress",
        "--search",
        "grid",
        "--scales",
        "0.9:1.1:0.05",
    ]
    result = invoke(*base, "--out", tmp_path / "ros", "--target-size", "ros")
    assert result.exit_code == 0, result.output
    document = json.loads((tmp_path / "ros" / "scale.json").read_text())
    assert document["E_est"] == pytest.approx((SOURCE_LWH * 0.875).tolist())
    assert document["expected_size"]["source_profile"] == "waymo"
    # what pretrain --size-norm ros records (test_model_card checks a real checkpoint)
    card = {"source_mean_lwh_m": [4.0, 2.0, 1.6], "ros_range": [0.7, 0.9], "size_norm": "ros"}
    (model / "model.json").write_text(json.dumps({"card": card}))
    result = invoke(*base, "--out", tmp_path / "ros2", "--target-size", "ros")
    assert result.exit_code == 0, result.output
    document = json.loads((tmp_path / "ros2" / "scale.json").read_text())
    assert document["E_est"] == pytest.approx([3.2, 1.6, 1.28])  # measured mean x mean factor 0.8
    result = invoke(*base, "--out", tmp_path / "x", "--target-size", "4,2,1.5")
    assert result.exit_code == 0 and json.loads((tmp_path / "x" / "scale.json").read_text())[
        "E_est"
    ] == [4, 2, 1.5]
    result = invoke(*base, "--out", tmp_path / "bad", "--target-size", "4,2")
    assert result.exit_code == 2 and "--target-size" in result.output


def test_cli_clipped_boundary_is_reported(sweep_setup):
    tmp_path, target, model = sweep_setup
    out = tmp_path / "clip"
    result = invoke(
        "--model", model, "--data", target, "--out", out, "--no-progress", "--scales", "0.8:1.1"
    )
    assert result.exit_code == 0, result.output
    assert "WARNING" in result.output and "clipped" in result.output
    document = json.loads((out / "scale.json").read_text())
    assert document["clipped"] == "high" and document["scale"] == pytest.approx(1.1)


def test_cli_no_detections_falls_back_to_no_scaling_or_fails_on_request(sweep_setup, monkeypatch):
    # the README's tiny run (8 frames, 1 epoch) gives no score >= 0.3: the loop must go on
    tmp_path, target, model = sweep_setup
    import stages.ptsn_sweep

    monkeypatch.setattr(
        stages.ptsn_sweep,
        "load_detector",
        lambda _: LawDetector(inverse_law(SOURCE_LWH), score=0.1),
    )
    out = tmp_path / "none"
    result = invoke("--model", model, "--data", target, "--out", out, "--no-progress")
    assert result.exit_code == 0, result.output
    assert "WARNING" in result.output and "no detections with score >= 0.3" in result.output
    document = json.loads((out / "scale.json").read_text())
    assert document["scale"] == 1.0 and document["fallback"] == "no-detections"
    assert document["E_pred_at_scale"] == [None, None, None] and document["monotone"] is None
    assert any("ŝ = 1" in w for w in document["warnings"])
    manifest = json.loads((out / "manifest.json").read_text())
    assert any("ŝ = 1" in note for note in manifest["notes"])

    strict = tmp_path / "strict"
    arguments = ["--model", model, "--data", target, "--no-progress", "--out", strict]
    result = invoke(*arguments, "--no-detections", "error")
    assert result.exit_code == 1 and "no detections" in result.output
    assert "more frames or epochs" in result.output and "--score-min" in result.output
    assert not strict.exists()


def test_crop_for_scales_keeps_every_point_some_scale_brings_into_range():
    rng = np.random.default_rng(2)
    points = rng.uniform(-120, 120, size=(20000, 4)).astype(np.float32)
    point_range = (0.0, -40.0, 70.4, 40.0)
    fixed_grid = lambda s: tuple(bound / s for bound in point_range)  # noqa: E731
    kept = ptsn.crop_for_scales(points, fixed_grid, 0.8, 1.4)
    assert 0 < len(kept) < len(points)
    scales = np.linspace(0.8, 1.4, 61)
    xy = points[:, None, :2] * scales[None, :, None]  # (n, S, 2)
    reachable = ((xy[..., 0] >= 0) & (xy[..., 0] <= 70.4) & (np.abs(xy[..., 1]) <= 40)).any(axis=1)
    assert reachable.sum() <= len(kept)
    kept_set = {tuple(p) for p in kept.tolist()}
    assert all(tuple(p) in kept_set for p in points[reachable].tolist())


def test_crop_follows_the_detectors_visible_range_above_scale_one():
    """For s > 1 the detector grows its grid by s (inference_config), so it still sees out to
    the trained range; a sweep above 1 must not crop away what the detector sees at its low end
    (a fixed-grid crop kept only x <= 70.4 / 1.1)."""
    from dali_cli.detector.config import DetectorConfig
    from dali_cli.detector.infer import inference_config, visible_range

    config = DetectorConfig()
    (x0, x1), (y0, y1) = config.x_range_m, config.y_range_m
    for scale in (0.8, 1.0, 1.1, 1.4):
        grid = inference_config(config, scale)
        bx0, by0, bx1, by1 = visible_range(config, scale)
        # a point at the visible bound, scaled by s, lands on the grid's bound
        assert np.isclose(bx1 * scale, grid.x_range_m[1]) and np.isclose(
            by0 * scale, grid.y_range_m[0]
        )
    assert visible_range(config, 1.1) == pytest.approx((x0, y0, x1, y1))
    points = np.array([[x1 - 1.0, 0.0, 0.0, 0.0], [x1 / 0.8 - 1.0, 0.0, 0.0, 0.0]], np.float32)
    kept = ptsn.crop_for_scales(points, lambda s: visible_range(config, s), 1.1, 1.4)
    assert len(kept) == 1 and kept[0, 0] == points[0, 0]  # seen at s = 1.1; the other at no s
    assert len(ptsn.crop_for_scales(points, lambda s: visible_range(config, s), 0.8, 1.4)) == 2


class FalseBoxDetector(LawDetector):
    """LawDetector plus one false box per non-empty frame: score 0.4, a fixed size (no law)."""

    FALSE_LWH = np.array([2.5, 1.2, 1.0])

    def predict(self, points_list, scale=1.0, mount_height_m=None):
        results = []
        for points, (boxes, scores) in zip(
            points_list, super().predict(points_list, scale, mount_height_m), strict=True
        ):
            if len(points):
                false = np.zeros((1, 7))
                false[0, 3:6] = self.FALSE_LWH
                boxes, scores = np.r_[boxes, false], np.r_[scores, np.float32(0.4)]
            results.append((boxes, scores))
        return results


@pytest.mark.parametrize("search", ["bracket", "grid"])
def test_sweep_keeps_its_boxes_and_reproduces_its_e_pred_from_them(search, sweep_setup,
                                                                    monkeypatch):  # fmt: skip
    """detections.parquet: at the sweep's own cut its E_pred(ŝ) is scale.json's exactly (same
    frames, same mean, same interpolation), at a stricter cut it drops the false boxes (the law's
    size at ŝ), and keeping it costs no detector pass."""
    from dali_cli.ptsn.detections import COLUMNS, e_pred_at

    tmp_path, target, model = sweep_setup
    detector = FalseBoxDetector(inverse_law(SOURCE_LWH))
    import stages.ptsn_sweep

    monkeypatch.setattr(stages.ptsn_sweep, "load_detector", lambda model_dir: detector)
    out = tmp_path / f"ptsn-{search}"
    result = invoke("--model", model, "--data", target, "--out", out, "--search", search,
                    "--no-progress")  # fmt: skip
    assert result.exit_code == 0, result.output
    document = json.loads((out / "scale.json").read_text())
    table = pq.read_table(out / "detections.parquet")
    columns = {name: table[name].to_numpy() for name in COLUMNS}
    assert set(np.unique(columns["frame"])) <= set(range(12)) and 3 not in columns["frame"]
    own, _ = e_pred_at(columns, document["scale"], document["score_min"], document["mean"])
    assert np.allclose(own, document["E_pred_at_scale"], rtol=0, atol=1e-6)
    confident, boxes = e_pred_at(columns, document["scale"], 0.7, document["mean"])
    assert np.allclose(confident, SOURCE_LWH / document["scale"], rtol=2e-3)
    assert not np.allclose(own, confident, rtol=1e-2)  # the false boxes moved the all-box mean
    assert 0 < boxes < np.count_nonzero(columns["score"] >= 0.3)
    sweep = pq.read_table(out / "sweep.parquet").to_pylist()
    assert sum(row["frame_passes"] for row in sweep) == document["detector_frames"]
    assert sum(calls for _, calls in detector.calls) == document["detector_frames"]


def test_e_pred_from_kept_boxes_groups_by_frame_and_interpolates_between_scales():
    from dali_cli.ptsn.detections import e_pred_at

    sizes = np.array([[4.0, 2.0, 1.0], [2.0, 1.0, 1.0], [6.0, 3.0, 2.0], [5.0, 2.0, 1.0]])
    columns = {
        "scale": np.array([1.0, 1.0, 1.0, 1.2]),
        "frame": np.array([0, 0, 1, 0]),
        "l": sizes[:, 0], "w": sizes[:, 1], "h": sizes[:, 2],
        "score": np.array([0.9, 0.5, 0.9, 0.9], np.float32),
    }  # fmt: skip
    at_one, count = e_pred_at(columns, 1.0, 0.3)  # frames' means (3, 1.5, 1) and (6, 3, 2)
    assert np.allclose(at_one, [4.5, 2.25, 1.5]) and count == 3
    pooled, _ = e_pred_at(columns, 1.0, 0.3, "pooled")
    assert np.allclose(pooled, [4.0, 2.0, 4.0 / 3])
    strict, count = e_pred_at(columns, 1.0, 0.7)
    assert np.allclose(strict, [5.0, 2.5, 1.5]) and count == 2
    between, _ = e_pred_at(columns, 1.1, 0.7)  # halfway to scale 1.2's (5, 2, 1)
    assert np.allclose(between, [5.0, 2.25, 1.25])
    nothing, count = e_pred_at(columns, 1.0, 0.95)
    assert np.isnan(nothing).all() and count == 0
