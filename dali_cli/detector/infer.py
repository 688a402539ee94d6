"""Inference: decode head maps into boxes, the `Detector` (checkpoint load + predict with PTSN
scaling), and `predict_frameset` for whole frame sets.

Checkpoint directory: `model.pt` (state dict) + `model.json` (config, provenance, metrics) +
`manifest.json` (written by the stage runner).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from dali_cli.detector.config import DetectorConfig
from dali_cli.detector.model import PillarCenterNet
from dali_cli.detector.refine import BoxRefiner, refine_boxes
from dali_cli.detector.targets import gather_cells, peaks_and_boxes
from dali_cli.geometry import (
    ground_to_sensor,
    scale_ground_points,
    sensor_to_ground,
    unscale_ground_boxes,
    wrap_angle,
)
from dali_cli.store.artifacts import ArtifactError, BoxTable, FrameSet
from dali_cli.store.model_card import ModelCard, read_meta

WEIGHTS_NAME = "model.pt"
META_NAME = "model.json"


def decode(
    maps: dict[str, torch.Tensor],
    config: DetectorConfig,
    refiner: BoxRefiner | None = None,
    points_list: list[np.ndarray] | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Head maps (B, dims, h, w) -> per frame (boxes (M, 7) float64 ground frame, scores (M,) float32).

    Peaks of the heatmap (3x3 local maxima), top-k, score = heat^(1-a) * iou^a, threshold, BEV NMS.
    With a `refiner` (second stage) and the frames' network-input points (P_b, >=3), the kept boxes
    are refined, scored score^(1-a2) * refined IoU^a2 (a2 = config.refine_alpha), thresholded and
    suppressed again.
    """
    from dali_cli.geometry import nms_bev

    heat_score, index, boxes = peaks_and_boxes(maps, config, config.top_k)  # (B, k), (B, k, 7)
    batch = heat_score.shape[0]
    iou = torch.sigmoid(gather_cells(maps["iou"].detach(), index)[..., 0])  # (B, k)
    alpha = config.iou_alpha
    score = (heat_score.pow(1 - alpha) * iou.pow(alpha)).float()  # (B, k)
    on_device = score.is_cuda  # threshold and NMS where the maps are; the kept boxes come back
    if not on_device:
        score, boxes = score.cpu().numpy(), boxes.cpu().numpy()  # numpy geometry on the host
    results = []
    for b in range(batch):  # frames: a few per batch
        if on_device:
            frame_boxes, frame_scores = device_nms(boxes[b], score[b], config)
        else:
            keep = score[b] >= config.score_threshold
            frame_boxes = boxes[b][keep]
            frame_scores = score[b][keep].astype(np.float32)
            frame_boxes[:, 6] = wrap_angle(frame_boxes[:, 6])
            kept = nms_bev(frame_boxes, frame_scores, config.nms_iou)
            frame_boxes, frame_scores = frame_boxes[kept], frame_scores[kept]
        if refiner is not None:
            frame_boxes, frame_scores = rescore_refined(
                refiner, points_list[b], frame_boxes, frame_scores, config
            )
        results.append((frame_boxes, frame_scores))
    return results


def device_nms(
    boxes: torch.Tensor, score: torch.Tensor, config: DetectorConfig
) -> tuple[np.ndarray, np.ndarray]:
    """One frame's top-k boxes (k, 7) and scores (k,) on a GPU -> the boxes (M, 7) float64 and
    scores (M,) float32 that pass the score threshold and BEV NMS (box_ops), copied to the host."""
    from dali_cli.detector import box_ops

    keep = score >= config.score_threshold
    frame_boxes, frame_scores = boxes[keep].double(), score[keep]
    frame_boxes[:, 6] = box_ops.wrap_angle(frame_boxes[:, 6])
    kept = box_ops.nms_bev(frame_boxes, frame_scores, config.nms_iou)
    return frame_boxes[kept].cpu().numpy(), frame_scores[kept].cpu().numpy().astype(np.float32)


def rescore_refined(
    refiner: BoxRefiner,
    points: np.ndarray,
    boxes: np.ndarray,
    scores: np.ndarray,
    config: DetectorConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """One frame's first-stage boxes (M, 7) and scores (M,) -> refined, rescored, thresholded and
    suppressed boxes and scores (see refine.py)."""
    from dali_cli.geometry import nms_bev

    refined, iou = refine_boxes(refiner, points, boxes, config)
    alpha = config.refine_alpha
    rescored = (scores ** (1 - alpha) * iou**alpha).astype(np.float32)
    keep = np.flatnonzero(rescored >= config.score_threshold)
    refined, rescored = refined[keep], rescored[keep]
    kept = nms_bev(refined, rescored, config.nms_iou)
    return refined[kept], rescored[kept]


def to_network_input(points_list: list[np.ndarray], mount_height_m: float, scale: float = 1.0):
    """Sensor-frame points -> ground-frame, PTSN-scaled (x, y, z, i) tensor (P, 4), batch index (P,)
    (geometry.sensor_to_ground then geometry.scale_ground_points, in float32)."""
    arrays = [
        scale_ground_points(
            sensor_to_ground(np.asarray(points, np.float32).reshape(-1, 4), mount_height_m), scale
        )
        for points in points_list
    ]
    sizes = [len(a) for a in arrays]
    stacked = np.concatenate(arrays) if arrays else np.zeros((0, 4), np.float32)
    batch_index = np.repeat(np.arange(len(arrays)), sizes)
    return torch.from_numpy(stacked), torch.from_numpy(batch_index)


def ground_boxes_to_sensor(
    boxes: np.ndarray, mount_height_m: float, scale: float = 1.0
) -> np.ndarray:
    """Undo `to_network_input`: (M, 7) ground-frame boxes on s-scaled points -> sensor frame, unscaled."""
    return ground_to_sensor(unscale_ground_boxes(boxes, scale), mount_height_m)


def load_weights_only(path: Path, what: str, advice: str = ""):
    """torch.load of a file dali wrote, with the weights_only unpickler (tensors, numbers,
    strings, lists, dicts: no code can run); ArtifactError naming the file (and `advice`)
    otherwise."""
    from dali_cli.store.regular_files import UnreadableFileError, checked_size

    try:  # a regular file within the weights budget, by stat: a 4 GiB sparse model.pt is not read
        checked_size(path, what, "weights")
    except UnreadableFileError as error:
        raise ArtifactError(str(error)) from None
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # UnpicklingError, RuntimeError, IndexError on garbage, ...
        first = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise ArtifactError(
            f"{path}: not {what} (refused to load it: {first}); dali loads only plain weights "
            "it wrote itself" + (f"; {advice}" if advice else "")
        ) from None


def save_checkpoint(directory: str | Path, net: PillarCenterNet, meta: dict) -> None:
    """Write model.pt (weights) and model.json (config + meta) into `directory`."""
    from dali_cli.store.disk_space import save_torch

    directory = Path(directory)
    save_torch(net.state_dict(), directory / WEIGHTS_NAME)
    document = {"detector": net.config.name, "config": net.config.to_dict(), **meta}
    (directory / META_NAME).write_text(json.dumps(document, indent=2, default=str) + "\n")


def config_of(meta: dict, meta_path: Path) -> DetectorConfig:
    """The DetectorConfig of a model.json document (`meta`, read from `meta_path`); an
    ArtifactError naming the file when it has none or an invalid one."""
    try:
        values = dict(meta["config"])
        # checkpoints from before the second stage existed have no refiner weights
        values.setdefault("refine", False)
        # nor, from before the direction classifier, a direction: headings modulo pi
        values.setdefault("direction", False)
        return DetectorConfig.from_dict(values)
    except (KeyError, TypeError, ValueError) as error:
        raise ArtifactError(f"{meta_path}: invalid model description ({error})") from None


def read_config(model_dir: str | Path) -> DetectorConfig:
    """The DetectorConfig of a model directory's model.json, without loading its weights."""
    return config_of(read_meta(model_dir), Path(model_dir) / META_NAME)


class Detector:
    """A trained detector. `predict` takes sensor-frame points and returns sensor-frame boxes."""

    def __init__(
        self,
        net: PillarCenterNet,
        meta: dict | None = None,
        device: torch.device | None = None,
        precision: str = "fp32",
    ):
        """`device`: where the network runs (default: where its weights are); `precision`:
        fp32, or bf16 autocast (dali_cli.runtime.device.autocast)."""
        if device is None:  # where the weights are (a parameterless stand-in: the CPU)
            device = next((p.device for p in net.parameters()), torch.device("cpu"))
        self.device = device
        self.net = net.to(self.device).eval()
        self.config = net.config
        self.meta = meta or {}
        self.precision = precision

    def to(self, device: torch.device, precision: str = "fp32") -> Detector:
        """This detector on `device` with `precision` (the network is moved in place)."""
        self.device, self.precision = device, precision
        self.net.to(device)
        return self

    @property
    def card(self) -> ModelCard:
        """What training recorded about this model (source sensor and sizes, size norm)."""
        return ModelCard.from_meta(self.meta)

    @classmethod
    def load(
        cls, model_dir: str | Path, device: torch.device | None = None, precision: str = "fp32"
    ) -> Detector:
        """A checkpoint directory written by dali, on `device` (default: the CPU). Anything else
        (a missing or foreign file, a pickle that is not plain weights, weights of another
        shape) is an ArtifactError naming the file; weights are read with torch's weights_only
        loader, so no code runs."""
        model_dir = Path(model_dir)
        meta_path, weights_path = model_dir / META_NAME, model_dir / WEIGHTS_NAME
        meta = read_meta(model_dir)
        if not weights_path.is_file():
            raise ArtifactError(f"{weights_path}: not found (is {model_dir} a model directory?)")
        config = config_of(meta, meta_path)
        named = meta.get("detector", config.name)
        if named not in (config.name, "pillar-centerpoint-iou", "pillar-centerpoint-iou-refine"):
            raise ArtifactError(
                f"{meta_path}: field 'detector' is {str(named)[:80]!r}, not a dali detector "
                f"(this one is {config.name})"
            )
        net = PillarCenterNet(config)
        state = load_weights_only(weights_path, "dali model weights")
        try:
            net.load_state_dict(state)
        except (RuntimeError, TypeError, AttributeError) as error:
            raise ArtifactError(
                f"{weights_path}: weights do not fit {config.name} as {meta_path.name} describes "
                f"it ({str(error).splitlines()[0]})"
            ) from None
        return cls(net, meta, device=device or torch.device("cpu"), precision=precision)

    def visible_range(self, scale: float) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) in metres (sensor frame) the detector sees at PTSN scale `scale`."""
        return visible_range(self.config, scale)

    @torch.no_grad()
    def predict(
        self,
        points_list: list[np.ndarray],
        scale: float = 1.0,
        mount_height_m: float | None = None,
        batch_size: int = 4,
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Boxes and scores per frame: [(boxes (M, 7) float64, scores (M,) float32)].

        points_list: sensor-frame (n, 4) float32 arrays. With scale s (PTSN), the points are scaled
        by s about the ground (sensor z + mount_height_m, default the checkpoint's) before the
        network and the boxes divided by s afterwards, so boxes are always in the original frame.
        """
        mount = self.config.mount_height_m if mount_height_m is None else float(mount_height_m)
        if not scale > 0:
            raise ValueError(f"scale must be positive, got {scale}")
        from dali_cli.runtime.device import autocast

        config = inference_config(self.config, scale)
        refiner = getattr(self.net, "refiner", None) if config.refine else None
        results = []
        for start in range(0, len(points_list), batch_size):
            chunk = points_list[start : start + batch_size]
            points, batch_index = to_network_input(chunk, mount, scale)
            frames_points = (  # the second stage's input: network-frame points per frame
                [points[batch_index == b].numpy() for b in range(len(chunk))]
                if refiner is not None
                else None
            )
            points, batch_index = points.to(self.device), batch_index.to(self.device)
            with autocast(self.device, self.precision):  # the second stage's MLP too
                maps = self.net(points, batch_index, len(chunk), grid=config)
                decoded = decode(maps, config, refiner, frames_points)
            for boxes, scores in decoded:
                results.append((ground_boxes_to_sensor(boxes, mount, scale), scores))
        return results


def visible_range(config: DetectorConfig, scale: float) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) in metres of the original sensor frame: where a point must lie for the
    detector, run at PTSN scale `scale`, to see it (the `inference_config` grid divided by s).
    Monotone in s: every bound moves towards the sensor as s grows, so the range over a scale
    interval is the hull of its two ends."""
    grid = inference_config(config, scale)
    (x0, x1), (y0, y1) = grid.x_range_m, grid.y_range_m
    return (x0 / scale, y0 / scale, x1 / scale, y1 / scale)


def inference_config(config: DetectorConfig, scale: float) -> DetectorConfig:
    """The grid for points scaled by `scale` (PTSN): for s > 1 the x, y ranges grow by s, so the
    scaled cloud still covers the trained range in original coordinates (a car at 65 m scaled by
    1.18 lies at 77 m, beyond a 70.4 m grid). The network is fully convolutional, so the larger
    grid runs the same weights; only the area (and time) grows, by s^2. For s <= 1 the grid is
    kept: the scaled cloud already fits, and points from beyond the range come into view."""
    if scale <= 1.0:
        return config
    (x0, x1), (y0, y1) = config.x_range_m, config.y_range_m
    return dataclasses.replace(
        config, x_range_m=(x0 * scale, x1 * scale), y_range_m=(y0 * scale, y1 * scale)
    )


def predict_frameset(
    model_dir: str | Path,
    data_dir: str | Path,
    scale: float = 1.0,
    score_min: float = 0.0,
    progress: bool = True,
    batch_size: int = 4,
    sensors_path: str | Path | None = None,
    device: torch.device | None = None,
    precision: str = "fp32",
    executor=None,
    shards_dir: str | Path | None = None,
    threads: int | None = None,
) -> BoxTable:
    """Run the detector of `model_dir` on every frame of the FrameSet `data_dir` on `device`
    (default: the CPU) with `precision` (fp32 or bf16 autocast), in this process on `threads`
    torch threads (default: every core it may use) or (a parallel `executor` of
    dali_cli.executors) as shards written under `shards_dir`, one thread a worker.

    The ground (for the network and for PTSN scaling) is the frame set's sensor profile mount height.
    Returns a BoxTable with score and num_points (points of the original frame inside each box).
    """
    from tqdm import tqdm

    from dali_cli.labels.pseudo_labeler import FrameLabeler
    from dali_cli.runtime.device import set_inference_threads
    from dali_cli.sensors import get_profile

    set_inference_threads(threads)
    frames = FrameSet(data_dir)
    mount = (
        get_profile(frames.sensor, sensors_path).mount_height_m if frames.sensor else None
    )  # None: the checkpoint's
    predictor = FrameLabeler(
        str(model_dir), str(data_dir), scale, mount, None, score_min, 1.0, batch_size,
        Detector.load, raw=True, device=device, precision=precision,
    )  # fmt: skip
    ids, all_boxes, all_scores, all_counts = [], [], [], []
    bar = tqdm(total=len(frames), desc="predict", unit="frame", disable=not progress, leave=False)
    for labels in predictor.frame_labels(executor, shards_dir, frames):
        ids.extend([labels.frame_id] * len(labels.boxes))
        all_boxes.append(labels.boxes)
        all_scores.append(labels.scores)
        all_counts.append(labels.counts)
        bar.update(1)
    bar.close()
    if not ids:
        return BoxTable.empty()
    return BoxTable.from_arrays(
        np.asarray(ids),
        np.concatenate(all_boxes),
        score=np.concatenate(all_scores),
        num_points=np.concatenate(all_counts),
    )
