"""Test-time fusion: the detector run on a scan, on its mirror image (y -> -y) and at scales
about ŝ, and the passes' boxes merged by a weighted box fusion of rotated boxes.

The fusion follows ensemble-boxes' WBF (Solovyev et al. 2021) with MS3D++'s KBF heading rule:
boxes are clustered by rotated BEV IoU about the highest-scoring unassigned box, the fused centre
and size are the score-weighted means of the cluster, the heading is the cluster's mean axis
(doubled-angle mean) turned to the end the score-weighted majority of its members points to (an
average of angles would point sideways when members disagree by pi), and the fused score is the
mean score times min(members, passes) / passes, so a box only one pass of several found is
demoted. Pure numpy on `(N, 7)` boxes `x, y, z, l, w, h, yaw` (dali_cli.geometry).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dali_cli.geometry import bev_iou_pairs, nms_bev, overlapping_pairs, wrap_angle

DEFAULT_IOU = 0.55  # WBF's default clustering threshold (ensemble-boxes iou_thr)


def mirror_points(points: np.ndarray) -> np.ndarray:
    """The mirror image `(n, >=3)` of points `(n, >=3)` about the sensor's x-z plane (y -> -y)."""
    mirrored = np.array(points, copy=True)
    mirrored[:, 1] = -mirrored[:, 1]
    return mirrored


def mirror_boxes(boxes: np.ndarray) -> np.ndarray:
    """Boxes `(M, 7)` mirrored about the x-z plane: y -> -y, yaw -> -yaw (its own inverse)."""
    mirrored = np.array(boxes, dtype=np.float64, copy=True).reshape(-1, 7)
    mirrored[:, 1] = -mirrored[:, 1]
    mirrored[:, 6] = wrap_angle(-mirrored[:, 6])
    return mirrored


def cluster_boxes(
    boxes: np.ndarray, scores: np.ndarray, iou_threshold: float
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster index `(N,)` int64 of each box `(N, 7)` and each cluster's seed `(K,)` int64 (an
    index into boxes): in descending score `(N,)`, each box not yet taken opens a cluster and
    takes every untaken box whose BEV IoU with it is >= `iou_threshold`."""
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    ranked = np.asarray(boxes, np.float64).reshape(-1, 7)[order]
    i, j = overlapping_pairs(ranked, ranked)
    below = i < j
    i, j = i[below], j[below]
    joined = bev_iou_pairs(ranked[i], ranked[j]) >= iou_threshold
    i, j = i[joined], j[joined]  # i ranks above j; i ascending
    starts = np.searchsorted(i, np.arange(len(ranked) + 1))
    cluster_of_rank = np.full(len(ranked), -1, np.int64)
    seeds = []
    for rank in range(len(ranked)):  # a loop over boxes, each step vectorized over neighbours
        if cluster_of_rank[rank] >= 0:
            continue
        neighbours = j[starts[rank] : starts[rank + 1]]
        cluster_of_rank[neighbours[cluster_of_rank[neighbours] < 0]] = len(seeds)
        cluster_of_rank[rank] = len(seeds)
        seeds.append(rank)
    cluster = np.empty(len(ranked), np.int64)
    cluster[order] = cluster_of_rank
    return cluster, order[np.asarray(seeds, np.int64)]


def vote_heading(yaw: np.ndarray, weight: np.ndarray, cluster: np.ndarray, seed_yaw: np.ndarray):
    """Fused yaw `(K,)` of K clusters from member yaws `(N,)`, weights `(N,)` and cluster index
    `(N,)`: the weighted mean axis (angles doubled, so yaw and yaw + pi agree), turned to the end
    the weighted majority of members points to; a tie goes to the seed's end (`seed_yaw` `(K,)`)."""
    count = len(seed_yaw)
    sin2 = np.bincount(cluster, weight * np.sin(2 * yaw), count)  # (K,)
    cos2 = np.bincount(cluster, weight * np.cos(2 * yaw), count)  # (K,)
    axis = 0.5 * np.arctan2(sin2, cos2)  # (K,) in (-pi/2, pi/2]
    forward = np.sign(np.cos(yaw - axis[cluster]))  # (N,) +1: along the axis, -1: against it
    vote = np.bincount(cluster, weight * forward, count)  # (K,)
    seed_side = np.sign(np.cos(seed_yaw - axis))  # (K,)
    side = np.where(vote != 0, np.sign(vote), np.where(seed_side != 0, seed_side, 1.0))
    return wrap_angle(np.where(side > 0, axis, axis + np.pi))


def fuse_boxes(
    boxes: np.ndarray, scores: np.ndarray, passes: int, iou_threshold: float = DEFAULT_IOU
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted box fusion of rotated boxes: every pass's boxes of one frame, stacked `(N, 7)`
    with scores `(N,)` in [0, 1], -> fused boxes `(K, 7)` float64 and scores `(K,)` float32 in
    [0, 1], by descending score. Centre and size: the score-weighted means of a cluster
    (`cluster_boxes`); yaw: `vote_heading`; score: mean score x min(members, passes) / passes."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    scores = np.asarray(scores, np.float64).reshape(-1)
    if len(boxes) == 0:
        return np.zeros((0, 7)), np.zeros(0, np.float32)
    cluster, seed = cluster_boxes(boxes, scores, iou_threshold)  # (N,), (K,)
    count = len(seed)
    members = np.bincount(cluster, minlength=count).astype(np.float64)  # (K,)
    # a cluster of zero scores is weighted evenly, not divided by zero
    weight = np.where(np.bincount(cluster, scores, count)[cluster] > 0, scores, 1.0)  # (N,)
    total = np.bincount(cluster, weight, count)  # (K,)
    fused = np.stack(
        [np.bincount(cluster, weight * boxes[:, d], count) / total for d in range(6)], axis=1
    )  # (K, 6) x, y, z, l, w, h
    yaw = vote_heading(boxes[:, 6], weight, cluster, boxes[seed, 6])  # (K,)
    mean_score = np.bincount(cluster, scores, count) / members  # (K,)
    fused_score = mean_score * np.minimum(members, passes) / passes  # (K,)
    order = np.argsort(-fused_score, kind="stable")
    out = np.concatenate([fused, yaw[:, None]], axis=1)[order]  # (K, 7)
    return out, np.clip(fused_score[order], 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class TestTimeFusion:
    """Which passes to run and fuse: the scan and, with `flip`, its mirror image, each at ŝ x
    every factor of `scale_factors`; `iou_threshold` clusters the passes' boxes (`fuse_boxes`);
    the fused boxes go through BEV NMS at the detector's own threshold (a box that joined no
    cluster would otherwise double a fused one)."""

    __test__ = False  # not a pytest class despite its name

    flip: bool = False
    scale_factors: tuple[float, ...] = (1.0,)
    iou_threshold: float = DEFAULT_IOU

    @property
    def passes(self) -> list[tuple[float, bool]]:
        """(scale factor, mirrored) of every detector pass."""
        return [
            (f, m) for f in self.scale_factors for m in ((False, True) if self.flip else (False,))
        ]

    @property
    def active(self) -> bool:
        """More than one pass: a single unmirrored pass at ŝ is the detector as it is."""
        return len(self.passes) > 1 or self.passes[0] != (1.0, False)

    def record(self) -> dict:
        """The parameters as a manifest records them."""
        return {
            "flip": self.flip,
            "scale_factors": list(self.scale_factors),
            "iou": self.iou_threshold,
        }

    def predict(
        self,
        detector,
        points_list: list[np.ndarray],
        scale: float,
        mount_height_m: float | None = None,
        batch_size: int = 4,
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """`detector.predict`'s result for `points_list` (sensor-frame `(n, 4)` arrays) at PTSN
        scale `scale`: per frame the fused boxes `(K, 7)` in the original frame and scores `(K,)`."""
        per_pass = []
        for factor, mirrored in self.passes:  # a few passes, each over every frame
            clouds = [mirror_points(p) for p in points_list] if mirrored else points_list
            found = detector.predict(clouds, scale * factor, mount_height_m, batch_size)
            if mirrored:
                found = [(mirror_boxes(boxes), scores) for boxes, scores in found]
            per_pass.append(found)
        nms_iou = detector.config.nms_iou
        results = []
        for frame in zip(*per_pass, strict=True):
            boxes = np.concatenate([np.asarray(b, np.float64).reshape(-1, 7) for b, _ in frame])
            scores = np.concatenate([np.asarray(s, np.float64).reshape(-1) for _, s in frame])
            fused, fused_scores = fuse_boxes(boxes, scores, len(self.passes), self.iou_threshold)
            kept = nms_bev(fused, fused_scores, nms_iou)
            results.append((fused[kept], fused_scores[kept]))
        return results


def fusion_of(tta: tuple[bool, tuple[float, ...], float] | None) -> TestTimeFusion | None:
    """The TestTimeFusion of the commands' (flip, scale factors, IoU) options; None when they
    ask for the detector's single pass at ŝ."""
    if tta is None:
        return None
    flip, factors, iou = tta
    fusion = TestTimeFusion(bool(flip), tuple(float(f) for f in factors), float(iou))
    return fusion if fusion.active else None
