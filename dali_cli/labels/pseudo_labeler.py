"""The per-frame part of pseudo-labelling (stages.pseudo_label): run the detector on batches of
target frames at the PTSN scale, drop implausible boxes, cut scores, BEV NMS, count the
original points in each box. In this process, or as shards on an executor's workers (dali_cli.executors),
each loading the detector once; the batches are the same either way (shards are whole batches),
so the labels are too."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.labels import plausibility
from dali_cli.runtime.errors import StageError


@dataclass
class FrameLabels:
    """One frame's pseudo labels: boxes (K, 7) float64, scores (K,) float32, original points in
    each box (K,) int32; boxes above the score cut dropped as implausible; detector seconds (a batch's time is carried by its first frame)."""

    frame_id: str
    boxes: np.ndarray
    scores: np.ndarray
    counts: np.ndarray
    implausible: int
    seconds: float


def label_frame(
    boxes: np.ndarray, scores: np.ndarray, points: np.ndarray, score_min: float, nms_iou: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame's pseudo labels: boxes (K, 7), scores (K,), in-box point counts (K,) int32.

    boxes (M, 7) are already de-scaled to the original frame; points (n, 4) are the original ones.
    """
    from dali_cli.geometry import count_points_in_boxes, nms_bev

    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    scores = np.asarray(scores, np.float32).reshape(-1)
    keep = scores >= score_min
    boxes, scores = boxes[keep], scores[keep]
    kept = nms_bev(boxes, scores, nms_iou)
    boxes, scores = boxes[kept], scores[kept]
    return boxes, scores, count_points_in_boxes(points, boxes)


@dataclass(frozen=True)
class FrameLabeler:
    """What labelling a frame needs (picklable: it is also the executors' worker factory);
    `loader(model_dir)` returns the detector (an object with `predict`). `raw`: the detector's
    predictions as they are (dali eval): only the score cut, no plausibility check, no NMS."""

    model_dir: str
    target_dir: str
    scale: float
    mount_height_m: float | None
    max_range_m: float | None
    score_min: float
    nms_iou: float
    batch_size: int
    loader: Callable
    raw: bool = False
    device: object = (
        None  # a --device spec (str, resolved where the detector loads) or a torch.device
    )
    precision: str = "fp32"
    fusion: object = None  # a detector.fusion.TestTimeFusion: several passes, fused

    def load(self):
        """The detector, loaded and placed on this process's device (dali_cli.runtime.device)."""
        from dali_cli.runtime.device import inference_device, place

        device = self.device
        if device is None or isinstance(device, str):
            device = inference_device(device or "cpu", self.precision)
        return place(self.loader(self.model_dir), device, self.precision)

    def label_batch(self, detector, batch: list[tuple[str, np.ndarray]]) -> list[FrameLabels]:
        """Labels of a batch of (frame_id, points (n, 4)) frames, in order."""
        from dali_cli.geometry import count_points_in_boxes

        started = time.perf_counter()
        predictions = self.predict(detector, [points for _, points in batch])
        seconds = time.perf_counter() - started
        labels = []
        for (frame_id, points), (boxes, scores) in zip(batch, predictions, strict=True):
            if self.raw:
                keep = scores >= self.score_min
                boxes, scores = boxes[keep], scores[keep]
                counts = count_points_in_boxes(points, boxes)
                labels.append(FrameLabels(frame_id, boxes, scores, counts, 0, seconds))
                seconds = 0.0
                continue
            boxes, scores, implausible = self.plausible(boxes, scores)
            boxes, scores, counts = label_frame(boxes, scores, points, self.score_min, self.nms_iou)
            labels.append(FrameLabels(frame_id, boxes, scores, counts, implausible, seconds))
            seconds = 0.0
        return labels

    def predict(
        self, detector, points_list: list[np.ndarray]
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Every frame's [(boxes (M, 7) in the original frame, scores (M,))]: the detector run at
        ŝ on the points (with `fusion`, its passes fused)."""
        if self.fusion is not None and self.fusion.active:
            predictions = self.fusion.predict(
                detector, points_list, self.scale, self.mount_height_m, len(points_list)
            )
        else:
            predictions = detector.predict(
                points_list, scale=self.scale, mount_height_m=self.mount_height_m
            )
        if len(predictions) != len(points_list):
            raise StageError(
                f"{self.model_dir}: detector returned {len(predictions)} results for "
                f"{len(points_list)} frames"
            )
        return [
            (np.asarray(boxes).reshape(-1, 7), np.asarray(scores).reshape(-1))
            for boxes, scores in predictions
        ]

    def plausible(
        self, boxes: np.ndarray, scores: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """One frame's boxes (K, 7) and scores (K,), implausible boxes dropped first (before
        NMS: one absurd box with a high score would suppress the others), and how many of those
        had a score above the cut."""
        sane = plausibility.plausible(boxes, self.max_range_m)
        implausible = int(np.count_nonzero(~sane & (scores >= self.score_min)))
        return boxes[sane], scores[sane], implausible

    def batches(self, frames: Iterator[tuple[str, np.ndarray]]) -> Iterator[list]:
        buffer = []
        for item in frames:
            buffer.append(item)
            if len(buffer) == self.batch_size:
                yield buffer
                buffer = []
        if buffer:
            yield buffer

    def frame_labels(self, executor, directory: Path, target) -> Iterator[FrameLabels]:
        """Labels of every frame of `target` (a FrameSet) in order: in this process when the
        executor is serial, else as shards (whole batches) written under `directory`."""
        if executor is None or executor.serial:
            detector = self.load()
            for batch in self.batches(target.iter_frames()):
                yield from self.label_batch(detector, batch)
            return
        from dali_cli.executors import plan_shards, shard_results

        shards = plan_shards(target.frame_ids, executor.workers, multiple=self.batch_size)
        for shard, shard_dir, _ in shard_results(executor, self, shards, directory):
            yield from _read_labels(shard_dir, shard.frame_ids)

    def __call__(self) -> _LabelWorker:
        """An executor worker: the detector, loaded once, on one thread (one worker per core)."""
        import torch

        from dali_cli.executors import count_load
        from dali_cli.store.artifacts import FrameSet

        torch.set_num_threads(1)
        count_load("detector")
        return _LabelWorker(self, self.load(), FrameSet(self.target_dir))


class _LabelWorker:
    def __init__(self, labeler: FrameLabeler, detector, frames):
        self.labeler, self.detector, self.frames = labeler, detector, frames

    def run(self, shard, directory: Path) -> dict:
        """labels.npz of the shard: frame (index in the shard) per box, boxes, scores, counts;
        per frame: implausible boxes, detector seconds."""
        from dali_cli.executors import naming_frames

        frames = self.frames.iter_frames(range(shard.start, shard.stop))
        labels: list[FrameLabels] = []
        for batch_ids in self.labeler.batches(iter(shard.frame_ids)):
            with naming_frames(*batch_ids):
                batch = [next(frames) for _ in batch_ids]
                labels.extend(self.labeler.label_batch(self.detector, batch))
        np.savez(
            directory / "labels.npz",
            frame=np.repeat(np.arange(len(labels)), [len(x.boxes) for x in labels]),
            boxes=np.concatenate([x.boxes for x in labels]).reshape(-1, 7),
            scores=np.concatenate([x.scores for x in labels]).astype(np.float32),
            counts=np.concatenate([x.counts for x in labels]).astype(np.int32),
            implausible=[x.implausible for x in labels],
            seconds=[x.seconds for x in labels],
        )
        return {}


def _read_labels(directory: Path, frame_ids: tuple[str, ...]) -> Iterator[FrameLabels]:
    with np.load(directory / "labels.npz") as stored:
        data = {name: stored[name] for name in stored.files}
    ends = np.searchsorted(data["frame"], np.arange(len(frame_ids)), side="right")
    starts = np.r_[0, ends[:-1]]
    for i, frame_id in enumerate(frame_ids):
        part = slice(int(starts[i]), int(ends[i]))
        yield FrameLabels(
            frame_id,
            data["boxes"][part],
            data["scores"][part],
            data["counts"][part],
            int(data["implausible"][i]),
            float(data["seconds"][i]),
        )
