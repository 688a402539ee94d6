"""The detection cache: every (frame, scale) detector pass runs once, in batches."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np

from dali_cli.ptsn.spec import SCALE_DECIMALS, Predictor, PTSNError


class DetectionCache:
    """Detections per (frame index, scale), computed at most once.

    frames: indexable `frames[i] -> (n, 4) float32` (a list, or a lazy FrameSet reader).
    Keeps only boxes with score >= score_min (the caller's cut: the sweep's --score-min). `frame_passes` counts detector runs on one frame.
    """

    def __init__(
        self,
        detector: Predictor,
        frames,
        score_min: float,
        mount_height_m: float | None = None,
        batch_size: int = 8,
        progress: Callable[[int], None] | None = None,
    ):
        self.detector = detector
        self.frames = frames
        self.score_min = float(score_min)
        self.mount_height_m = mount_height_m
        self.batch_size = max(1, int(batch_size))
        self.progress = progress
        self._store: dict[tuple[int, float], tuple[np.ndarray, np.ndarray]] = {}
        self.frame_passes = 0
        self.seconds = 0.0

    @staticmethod
    def key(scale: float) -> float:
        return round(float(scale), SCALE_DECIMALS)

    def detections(
        self, scale: float, indices: Sequence[int]
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """(boxes (M, 7), scores (M,)) per frame of `indices` at `scale`; missing ones are run."""
        scale = self.key(scale)
        missing = [int(i) for i in indices if (int(i), scale) not in self._store]
        started = time.perf_counter()
        for start in range(0, len(missing), self.batch_size):
            batch = missing[start : start + self.batch_size]
            points = [self.frames[i] for i in batch]
            results = self.detector.predict(points, scale=scale, mount_height_m=self.mount_height_m)
            if len(results) != len(batch):
                raise PTSNError(f"detector returned {len(results)} results for {len(batch)} frames")
            for index, (boxes, scores) in zip(batch, results, strict=True):
                boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
                scores = np.asarray(scores, np.float32).reshape(-1)
                keep = scores >= self.score_min
                self._store[(index, scale)] = (boxes[keep], scores[keep])
            self.frame_passes += len(batch)
            if self.progress is not None:
                self.progress(len(batch))
        self.seconds += time.perf_counter() - started
        return [self._store[(int(i), scale)] for i in indices]

    def sizes(self, scale: float, indices: Sequence[int]) -> list[np.ndarray]:
        """De-scaled sizes `(M, 3)` per frame."""
        return [boxes[:, 3:6] for boxes, _ in self.detections(scale, indices)]

    @property
    def scales(self) -> list[float]:
        return sorted({scale for _, scale in self._store})
