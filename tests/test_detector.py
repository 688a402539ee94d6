"""Tests of the CPU detector: shapes, target/decoding round trip, exact PTSN de-scaling, a tiny
overfit, checkpoint round trip, resume, augmentations and SN/ROS consistency, the pretrain CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from toy_scenes import SMALL_NET as SMALL
from toy_scenes import place_cars, scan, write_toy_dataset

from dali_cli.cli import main
from dali_cli.detector import (
    Augmentation,
    Detector,
    DetectorConfig,
    PillarCenterNet,
    TrainSettings,
    augment,
    load_labeled,
    predict_frameset,
    save_checkpoint,
    size_normalize,
    train,
)
from dali_cli.detector.infer import decode, inference_config
from dali_cli.detector.targets import (
    REGRESSION,
    build_targets,
    detection_loss,
    peak_iou_loss,
    regression_to_boxes,
)
from dali_cli.geometry import count_points_in_boxes, iou_3d, point_box_indices, wrap_angle
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import FrameSet

PLACE = dict(x_range_m=(6.0, 22.0), y_range_m=(-9.0, 9.0))
SCAN = dict(beams=32, points_per_beam=400, azimuth_range_deg=(-60.0, 60.0))


@pytest.fixture(scope="module")
def kitti():
    return get_profile("kitti")


@pytest.fixture(scope="module")
def toy_dir(tmp_path_factory, kitti):
    directory = tmp_path_factory.mktemp("toy")
    write_toy_dataset(directory, kitti, frames=4, seed=3, cars_per_frame=4, **PLACE, **SCAN)
    return directory


def toy_place(rng, kitti, count=4):
    return place_cars(rng, count, kitti.car_mean_lwh_m, kitti.mount_height_m, *PLACE.values())


def test_forward_shapes():
    config = DetectorConfig(**SMALL)
    net = PillarCenterNet(config)
    points = torch.rand(500, 4) * torch.tensor([25.6, 25.6, 3.0, 1.0]) - torch.tensor(
        [0, 12.8, 1.0, 0]
    )
    batch_index = torch.arange(2).repeat_interleave(250)
    maps = net(points, batch_index, 2)
    h, w = config.head_size
    assert {name: tuple(v.shape) for name, v in maps.items()} == {
        "heatmap": (2, 1, h, w), "offset": (2, 2, h, w), "z": (2, 1, h, w),
        "size": (2, 3, h, w), "rot": (2, 2, h, w), "iou": (2, 1, h, w), "dir": (2, 2, h, w),
    }  # fmt: skip
    assert h * config.cell_m >= 25.6 and w * config.cell_m >= 25.6


def perfect_maps(boxes_list, config):
    """Head maps that encode exactly `boxes_list` (ground frame), built from the training targets."""
    targets = build_targets(boxes_list, config)
    heat = targets.heatmap.clamp(1e-6, 1 - 1e-6)
    maps = {"heatmap": torch.log(heat / (1 - heat)), "iou": torch.full_like(heat, 20.0)}
    batch, (h, w) = len(boxes_list), config.head_size
    regression = torch.zeros(batch, 8, h * w)
    direction = torch.zeros(batch, 2, h * w)
    for b in range(batch):
        valid = targets.mask[b]
        regression[b][:, targets.index[b][valid]] = targets.regression[b][valid].T
        cells, bins = targets.index[b][valid], targets.direction[b][valid]
        direction[b, bins, cells] = 20.0  # the true bin's logit far above the other's
    regression = regression.view(batch, 8, h, w)
    split = dict(zip(REGRESSION, regression.split([2, 1, 3, 2], dim=1), strict=True))
    direction_maps = {"dir": direction.view(batch, 2, h, w)} if config.direction else {}
    return {**maps, **split, **direction_maps}


@pytest.mark.parametrize("radius", [0, 1])
def test_targets_decode_round_trip(kitti, radius):
    config = DetectorConfig(**SMALL, regression_radius_cells=radius)
    rng = np.random.default_rng(0)
    boxes_list = [
        toy_place(rng, kitti, 5) + [0, 0, kitti.mount_height_m, 0, 0, 0, 0] for _ in range(2)
    ]
    decoded = decode(perfect_maps(boxes_list, config), config)
    for boxes, (found, scores) in zip(boxes_list, decoded, strict=True):
        assert len(found) == len(boxes)
        assert (scores > 0.99).all()
        iou = iou_3d(boxes, found)
        assert np.allclose(iou.max(axis=1), 1.0, atol=1e-6)
        match = iou.argmax(axis=1)  # the direction bins give back each car's full heading
        assert np.allclose(wrap_angle(found[match, 6] - boxes[:, 6]), 0.0, atol=1e-6)


def test_decoding_without_a_direction_head_gives_the_axis_only(kitti):
    """A model from before the direction classifier: yaws within +-pi/2, the same boxes."""
    config = DetectorConfig(**SMALL, direction=False)
    rng = np.random.default_rng(1)
    boxes = toy_place(rng, kitti, 6) + [0, 0, kitti.mount_height_m, 0, 0, 0, 0]
    boxes[:3, 6] = wrap_angle(boxes[:3, 6] + np.pi)  # some face the sensor
    ((found, _),) = decode(perfect_maps([boxes], config), config)
    assert np.all(np.abs(found[:, 6]) <= np.pi / 2 + 1e-9)
    assert np.allclose(iou_3d(boxes, found).max(axis=1), 1.0, atol=1e-6)


def test_every_regressing_cell_decodes_to_its_nearest_object():
    """Around-centre regression: each cell once, owned by the nearest centre, decoding exactly."""
    config = DetectorConfig(**SMALL, regression_radius_cells=1)
    # two cars 0.9 m apart side by side (windows of 3x3 cells of 0.64 m overlap), one on the edge
    boxes = np.array(
        [
            [10.0, 0.0, 0.8, 4.0, 1.7, 1.5, 0.3],
            [10.1, 0.9, 0.8, 4.2, 1.8, 1.5, -0.2],
            [0.1, -12.7, 0.8, 3.9, 1.6, 1.5, 1.0],
        ]
    )
    targets = build_targets([boxes], config)
    valid = targets.mask[0].numpy()
    index = targets.index[0].numpy()[valid]
    assert len(index) == len(np.unique(index))  # no cell regresses two objects
    decoded = regression_to_boxes(
        targets.regression[0][valid].double(), targets.index[0][valid], config
    )
    truth = targets.boxes[0][valid]
    assert np.allclose(decoded[:, :6].numpy(), truth[:, :6], atol=1e-5)
    assert np.allclose(np.cos(2 * (decoded[:, 6].numpy() - truth[:, 6])), 1.0, atol=1e-6)
    w = config.head_size[1]
    cell_centre = np.stack([(index % w + 0.5), (index // w + 0.5)], 1) * config.cell_m
    cell_centre += [config.x_range_m[0], config.y_range_m[0]]
    distance = np.linalg.norm(cell_centre[:, None, :] - boxes[None, :, :2], axis=2)  # (C, 3)
    owner = np.argmin(distance, axis=1)
    assert np.allclose(truth, boxes[owner])
    weight = targets.weight[0].numpy()[valid]
    assert weight.max() == 1.0 and (weight == 1.0).sum() == 3  # the three centre cells
    assert 3 < len(index) < 27  # the edge car's window is cut, the overlap is shared


class BoundingBoxNet(torch.nn.Module):
    """A 'model whose boxes are known': one axis-aligned box around all points of each frame."""

    def __init__(self, config):
        super().__init__()
        self.config = config

    def forward(self, points, batch_index, batch_size, grid=None):
        boxes_list = []
        for b in range(batch_size):
            xyz = points[batch_index == b, :3].double().numpy()
            low, high = xyz.min(axis=0), xyz.max(axis=0)
            boxes_list.append(np.array([[*(low + high) / 2, *(high - low), 0.0]]))
        return perfect_maps(boxes_list, grid or self.config)


@pytest.mark.parametrize("scale", [0.8, 1.0, 1.25])
def test_predict_descaling_is_exact(scale, kitti):
    config = DetectorConfig(**SMALL, mount_height_m=kitti.mount_height_m)
    detector = Detector(BoundingBoxNet(config))
    rng = np.random.default_rng(1)
    box = np.array([12.0, 2.0, -kitti.mount_height_m + 0.8, 4.0, 1.8, 1.6, 0.0])
    corners = np.array(np.meshgrid([-0.5, 0.5], [-0.5, 0.5], [-0.5, 0.5])).reshape(3, -1).T
    inner = rng.uniform(-0.5, 0.5, size=(50, 3))
    xyz = box[:3] + np.concatenate([corners, inner]) * box[3:6]
    points = np.concatenate([xyz, np.zeros((len(xyz), 1))], axis=1).astype(np.float32)
    (found, scores), = detector.predict([points], scale=scale)  # fmt: skip
    assert len(found) == 1
    assert np.allclose(found[0], box, atol=2e-5)  # float32 points


def test_ptsn_scaling_keeps_cars_near_the_range_end(kitti):
    """A car at 22 m of a 25.6 m grid, scaled by 1.25, lies at 27.5 m: the grid grows with s."""
    config = DetectorConfig(**SMALL, mount_height_m=kitti.mount_height_m)
    detector = Detector(BoundingBoxNet(config))
    box = np.array([22.0, -9.0, -kitti.mount_height_m + 0.8, 4.0, 1.8, 1.6, 0.0])
    corners = np.array(np.meshgrid([-0.5, 0.5], [-0.5, 0.5], [-0.5, 0.5])).reshape(3, -1).T
    xyz = box[:3] + corners * box[3:6]
    points = np.concatenate([xyz, np.zeros((len(xyz), 1))], axis=1).astype(np.float32)
    for scale in (1.25, 1.4):
        (found, _), = detector.predict([points], scale=scale)  # fmt: skip
        assert len(found) == 1 and np.allclose(found[0], box, atol=2e-5)
    grown = inference_config(config, 1.25)
    assert grown.x_range_m == (0.0, 32.0) and grown.y_range_m == (-16.0, 16.0)
    assert grown.pillar_m == config.pillar_m and inference_config(config, 0.9) == config
    net = PillarCenterNet(config)
    points = torch.rand(300, 4) * torch.tensor([32.0, 32.0, 3.0, 1.0]) - torch.tensor(
        [0, 16.0, 1.0, 0]
    )
    maps = net.eval()(points, torch.zeros(300, dtype=torch.long), 1, grid=grown)
    assert maps["heatmap"].shape[-2:] == grown.head_size != config.head_size


def trained(toy_dir, epochs: float):
    """(data, net, result) of the small detector trained `epochs` on the toy frames."""
    config = DetectorConfig(**SMALL)
    data = load_labeled(toy_dir, config)
    torch.manual_seed(0)
    net = PillarCenterNet(config)
    settings = TrainSettings(epochs=epochs, batch_size=2, lr=5e-3, seed=0, log_every=1)
    result = train(net, [data], [Augmentation.none()], settings, progress=False)
    return data, net, result


@pytest.fixture(scope="module")
def overfit(toy_dir):
    return trained(toy_dir, epochs=40)


@pytest.fixture(scope="module")
def briefly_trained(toy_dir):
    """A net whose weights training has moved (what a checkpoint round trip compares), without
    the cost of training it to convergence (`overfit`, a slow test)."""
    return trained(toy_dir, epochs=3)


@pytest.mark.slow  # trains the detector to convergence
def test_overfit_tiny_set(overfit):
    data, net, result = overfit
    losses = [row["loss"] for row in result.log]
    assert np.mean(losses[-10:]) < 0.2 * np.mean(losses[:3])
    detector = Detector(net)
    sensor_frames = [p - np.array([0, 0, data.mount_height_m, 0], np.float32) for p in data.points]
    true_scores, false_scores, total = [], [], 0
    for gt, (found, scores) in zip(data.boxes, detector.predict(sensor_frames), strict=True):
        gt = gt - np.array([0, 0, data.mount_height_m, 0, 0, 0, 0])
        iou = iou_3d(found, gt)  # (M, G)
        best = iou.argmax(axis=1)
        hit = iou.max(axis=1) >= 0.7
        first = np.zeros(len(found), bool)  # the best-scoring hit of each ground-truth box
        for g in range(len(gt)):
            candidates = np.flatnonzero(hit & (best == g))
            if len(candidates):
                first[candidates[np.argmax(scores[candidates])]] = True
        true_scores += scores[first].tolist()
        false_scores += scores[~first].tolist()
        total += len(gt)
    assert len(true_scores) == total  # every car found at 3D IoU >= 0.7 ...
    outranked = np.sum(np.asarray(false_scores) >= min(true_scores))
    assert outranked <= 1  # ... and ranked above (almost) every false positive: AP ~ 100


def test_checkpoint_round_trip(briefly_trained, tmp_path, toy_dir):
    _, net, _ = briefly_trained
    save_checkpoint(tmp_path, net, {"provenance": {"stage": "test"}})
    loaded = Detector.load(tmp_path)  # on the CPU; `net` where it trained (a GPU under auto):
    # compare on one device, where equal weights must give bit-equal boxes (a GPU's and the
    # CPU's arithmetic differ by ~1e-4 m: seen on an H200, docs/scale-out.md)
    frames = [np.asarray(p) for p in load_labeled(toy_dir, net.config).points]
    trained = Detector(net, device=torch.device("cpu"))
    for (a, sa), (b, sb) in zip(trained.predict(frames), loaded.predict(frames), strict=True):
        assert np.array_equal(a, b) and np.array_equal(sa, sb)
    table = predict_frameset(tmp_path, toy_dir, progress=False)
    assert len(table) > 0
    assert set(table.frame_id) <= {"000000", "000001", "000002", "000003"}
    frame = FrameSet(toy_dir).frame("000001")
    rows = table.for_frame("000001")
    assert np.array_equal(rows["num_points"], count_points_in_boxes(frame, rows.boxes))
    assert (rows["num_points"][rows["score"] >= 0.5] > 0).all()


def test_resume_continues_identically(toy_dir, tmp_path):
    config = DetectorConfig(**SMALL)
    data = load_labeled(toy_dir, config)
    settings = TrainSettings(epochs=3, batch_size=2, seed=1, log_every=1, checkpoint_every_s=0.0)

    def fresh():
        torch.manual_seed(0)
        return PillarCenterNet(config)

    reference = fresh()
    train(reference, [data], [Augmentation()], settings, progress=False)

    class Interrupt(Exception):
        pass

    def stop_at_step_3(row):
        if row["step"] == 3:
            raise Interrupt

    state = tmp_path / "state.pt"
    with pytest.raises(Interrupt):
        train(fresh(), [data], [Augmentation()], settings, state, "key", False, stop_at_step_3)
    resumed = fresh()
    result = train(resumed, [data], [Augmentation()], settings, state, "key", progress=False)
    assert result.resumed_from_step >= 2
    for a, b in zip(reference.state_dict().values(), resumed.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    other = train(fresh(), [data], [Augmentation()], settings, state, "other-key", progress=False)
    assert other.resumed_from_step == 0


def scene(kitti, seed=0):
    rng = np.random.default_rng(seed)
    boxes = toy_place(rng, kitti, 5)
    points = scan(boxes, kitti, **SCAN)
    points[:, 2] += kitti.mount_height_m
    boxes[:, 2] += kitti.mount_height_m
    return points, boxes


def inside_counts(points, boxes):
    return count_points_in_boxes(points, boxes)


@pytest.mark.parametrize("transform", ["flip", "rotate", "scale", "noise", "ros_shrink", "sn_grow"])
def test_augmentations_keep_points_in_their_boxes(transform, kitti):
    points, boxes = scene(kitti)
    before = point_box_indices(points, boxes)
    rng = np.random.default_rng(5)
    if transform == "flip":
        new_points, new_boxes = augment.flip_y(points, boxes)
    elif transform == "rotate":
        new_points, new_boxes = augment.rotate_scene(points, boxes, 0.7)
    elif transform == "scale":
        new_points, new_boxes = augment.scale_scene(points, boxes, 1.04)
    elif transform == "noise":
        new_points, new_boxes = augment.object_noise(points, boxes, rng)
    elif transform == "ros_shrink":
        factors = np.repeat(rng.uniform(0.75, 1.0, len(boxes))[:, None], 3, axis=1)
        new_points, new_boxes = augment.scale_objects(points, boxes, factors, margin_m=0.0)
        assert np.allclose(new_boxes[:, 3:6], boxes[:, 3:6] * factors)
    else:
        factors = rng.uniform(1.0, 1.3, size=(len(boxes), 3))
        new_points, new_boxes = augment.scale_objects(points, boxes, factors, margin_m=0.0)
    assert new_points.shape == points.shape and new_boxes.shape == boxes.shape
    after = point_box_indices(new_points, new_boxes, margin_m=1e-4)
    mine = before >= 0
    assert np.array_equal(after[mine], before[mine])  # every car point stays in its own box
    if transform in ("ros_shrink", "sn_grow"):
        bottom = lambda b: b[:, 2] - b[:, 5] / 2  # noqa: E731
        assert np.allclose(bottom(new_boxes), bottom(boxes))  # cars stay on the ground
        assert np.array_equal(
            new_points[~mine], points[~mine]
        )  # the rest of the scene is untouched


def test_size_normalization_shifts_the_mean(toy_dir):
    data = load_labeled(toy_dir, DetectorConfig(**SMALL))
    delta = np.array([0.77, 0.46, 0.20])
    normalized = size_normalize(data, delta)
    assert np.allclose(normalized.mean_lwh(), data.mean_lwh() + delta)
    for i, (points, boxes) in enumerate(zip(normalized.points, normalized.boxes, strict=True)):
        before = count_points_in_boxes(data.points[i], data.boxes[i])
        assert (
            count_points_in_boxes(points, boxes, margin_m=1e-4) >= before
        ).all()  # grown: none lost


def test_ground_truth_sampling_adds_non_overlapping_cars(toy_dir):
    from dali_cli.geometry import bev_iou

    data = load_labeled(toy_dir, DetectorConfig(**SMALL))
    database = augment.ObjectDatabase.build(data.points, data.boxes)
    assert len(database) > 0
    points, boxes = augment.sample_ground_truth(
        data.points[0], data.boxes[0], database, np.random.default_rng(0), target_count=8
    )
    assert len(boxes) > len(data.boxes[0])
    overlap = bev_iou(boxes, boxes)
    np.fill_diagonal(overlap, 0)
    assert (overlap == 0).all()
    assert (count_points_in_boxes(points, boxes) > 0).all()


def test_pretrain_cli(toy_dir, tmp_path):
    out = tmp_path / "iter0"
    runner = CliRunner()
    args = [
        "pretrain",
        "--source",
        str(toy_dir),
        "--out",
        str(out),
        "--epochs",
        "1",
        "--no-progress",
        "--batch-size",
        "4",
    ]
    result = runner.invoke(main, args)
    assert result.exit_code == 0, result.output
    for name in ("model.pt", "model.json", "train_log.parquet", "manifest.json"):
        assert (out / name).is_file()
    meta = json.loads((out / "model.json").read_text())
    assert meta["provenance"]["source_sensor"] == "kitti" and meta["train"]["steps"] == 1
    assert not (tmp_path / "iter0.resume").exists()
    again = runner.invoke(main, args)
    assert again.exit_code == 0 and "up to date" in again.output
    usage = runner.invoke(
        main, ["pretrain", "--source", str(toy_dir), "--out", str(out), "--size-norm", "sn"]
    )
    assert usage.exit_code == 2 and "--target-profile" in usage.output
    (tmp_path / "empty").mkdir()
    missing = runner.invoke(
        main, ["pretrain", "--source", str(tmp_path / "empty"), "--out", str(tmp_path / "x")]
    )
    assert missing.exit_code == 1 and "frames.zarr" in missing.output


def test_retired_config_keys_load_at_their_value_only():
    """model.json files of earlier models carry refine_passes 1, flip_test false and refine_flip
    true: they load; any other value is refused with the key named, and the written config no
    longer has them."""
    old = {**DetectorConfig(**SMALL).to_dict(), "refine_passes": 1, "flip_test": False,
           "refine_flip": True}  # fmt: skip
    assert DetectorConfig.from_dict(old) == DetectorConfig(**SMALL)
    assert not {"refine_passes", "flip_test", "refine_flip"} & set(DetectorConfig().to_dict())
    for key, value in (("refine_passes", 2), ("flip_test", True), ("refine_flip", False)):
        with pytest.raises(ValueError, match=key):
            DetectorConfig.from_dict({**old, key: value})


def test_peak_iou_loss_teaches_background_peaks_a_low_iou(kitti):
    """The IoU head's loss at heatmap peaks: ~0 when it says 1 at the objects and 0 elsewhere,
    large when it says 1 everywhere (background peaks have IoU 0 with every object)."""
    config = DetectorConfig(**SMALL, iou_peak_cells=32)
    rng = np.random.default_rng(7)
    boxes = toy_place(rng, kitti, 4) + [0, 0, kitti.mount_height_m, 0, 0, 0, 0]
    targets = build_targets([boxes], config)
    maps = perfect_maps([boxes], config)
    centres = torch.zeros(config.head_size).flatten()
    centres[targets.index[0][targets.mask[0]]] = 1.0
    maps["iou"] = (centres.view(1, 1, *config.head_size) * 40 - 20).float()
    assert peak_iou_loss(maps, targets, config) < 1e-3
    maps["iou"] = torch.full_like(maps["iou"], 20.0)
    assert peak_iou_loss(maps, targets, config) > 1.0
    total, terms = detection_loss(maps, targets, config)
    assert "iou_peaks" in terms and terms["loss"] >= terms["iou_peaks"]


def test_checkpoint_without_refine_key_loads_as_one_stage(tmp_path):
    """model.json written before the second stage existed has no "refine": it loads without one."""
    config = DetectorConfig(**SMALL, refine=False)
    net = PillarCenterNet(config)
    save_checkpoint(tmp_path, net, {"provenance": {"stage": "test"}})
    meta = json.loads((tmp_path / "model.json").read_text())
    del meta["config"]["refine"]
    (tmp_path / "model.json").write_text(json.dumps(meta))
    loaded = Detector.load(tmp_path)
    assert loaded.config.refine is False and loaded.net.refiner is None


def test_detector_scales_about_the_ground_as_geometry_does():
    """One PTSN transform: the network input is geometry.scale_points_about_ground's cloud in the
    ground frame, and the detector's de-scaling is geometry.descale_boxes_about_ground."""
    from dali_cli import geometry
    from dali_cli.detector.infer import ground_boxes_to_sensor, to_network_input

    rng = np.random.default_rng(4)
    points = rng.uniform(-40, 40, (500, 4)).astype(np.float32)
    mount, scale = 1.73, 1.17
    network, batch = to_network_input([points, points[:10]], mount, scale)
    expected = geometry.sensor_to_ground(
        geometry.scale_points_about_ground(points, scale, mount), mount
    )
    np.testing.assert_allclose(network.numpy()[:500], expected, rtol=1e-6, atol=1e-5)
    assert network.dtype == torch.float32 and batch.tolist() == [0] * 500 + [1] * 10
    boxes = np.c_[rng.uniform(-30, 30, (8, 3)), rng.uniform(1, 5, (8, 3)), rng.uniform(-3, 3, 8)]
    ground = geometry.sensor_to_ground(
        geometry.scale_boxes_about_ground(boxes, scale, mount), mount
    )
    np.testing.assert_allclose(ground_boxes_to_sensor(ground, mount, scale), boxes, atol=1e-9)
    np.testing.assert_array_equal(
        ground_boxes_to_sensor(ground, mount, scale),
        geometry.descale_boxes_about_ground(geometry.ground_to_sensor(ground, mount), scale, mount),
    )
