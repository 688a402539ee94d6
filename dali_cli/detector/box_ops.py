"""Rotated-box geometry on torch tensors, on whatever device they live (the GPU at training and
inference there): BEV intersection, BEV and 3D IoU, and greedy BEV non-maximum suppression.
dali_cli.geometry's numpy versions are the reference (tests: within 1e-6); these exist so that a
GPU run does not copy boxes to the host, and wait for it, for every IoU target and every NMS.

Boxes are (N, 7) x, y, z (centre), l, w, h, yaw; computed in float64. The intersection of two
convex rectangles is the convex hull of the corners of each inside the other and the crossings of
their edges (at most 4 + 4 + 16 candidates), ordered by angle about their centroid.
"""

from __future__ import annotations

import math

import torch

CORNER_SIGNS = ((0.5, 0.5), (-0.5, 0.5), (-0.5, -0.5), (0.5, -0.5))  # counter-clockwise
EPS = 1e-9
PAIR_BLOCK = 1 << 16  # pairs per block of the pairwise functions (memory ~ 24 candidates each)


def wrap_angle(angle: torch.Tensor) -> torch.Tensor:
    """Angles (rad) wrapped into [-pi, pi) in their dtype (dali_cli.geometry.wrap_angle's rule)."""
    wrapped = torch.remainder(angle + math.pi, 2.0 * math.pi) - math.pi
    return torch.where(wrapped >= math.pi, wrapped - 2.0 * math.pi, wrapped)


def bev_corners(boxes: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
    """(N, 4, 2) BEV corners, counter-clockwise, relative to `origin` (N, 2)."""
    signs = torch.tensor(CORNER_SIGNS, dtype=boxes.dtype, device=boxes.device)  # (4, 2)
    local = signs[None] * boxes[:, None, 3:5]  # (N, 4, 2)
    cos, sin = torch.cos(boxes[:, 6:7]), torch.sin(boxes[:, 6:7])  # (N, 1)
    x = cos * local[..., 0] - sin * local[..., 1] + (boxes[:, 0:1] - origin[:, 0:1])
    y = sin * local[..., 0] + cos * local[..., 1] + (boxes[:, 1:2] - origin[:, 1:2])
    return torch.stack([x, y], dim=-1)


def cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def inside(points: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """(P, K) bool: points (P, K, 2) inside (or on) the convex CCW quadrilaterals (P, 4, 2)."""
    start = corners[:, None, :, :]  # (P, 1, 4, 2)
    edge = torch.roll(corners, -1, dims=1)[:, None] - start  # (P, 1, 4, 2)
    side = cross(edge, points[:, :, None, :] - start)  # (P, K, 4): >= 0 left of every edge
    scale = edge.norm(dim=-1)  # tolerance in metres, not in metres squared
    return (side >= -EPS * scale).all(dim=-1)


def bev_intersection_pairs(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """BEV intersection area (N,) float64 (m^2) of row-wise box pairs a[i], b[i] (N, 7)."""
    a, b = a.double().reshape(-1, 7), b.double().reshape(-1, 7)
    origin = b[:, :2]  # b's centre: small coordinates even far from the sensor
    ca, cb = bev_corners(a, origin), bev_corners(b, origin)  # (P, 4, 2)
    a0, b0 = ca[:, :, None, :], cb[:, None, :, :]  # (P, 4, 1, 2), (P, 1, 4, 2)
    da = torch.roll(ca, -1, dims=1)[:, :, None, :] - a0
    db = torch.roll(cb, -1, dims=1)[:, None, :, :] - b0
    denominator = cross(da, db)  # (P, 4, 4)
    parallel = denominator.abs() < EPS
    safe = torch.where(parallel, torch.ones_like(denominator), denominator)
    t = cross(b0 - a0, db) / safe  # along a's edge
    u = cross(b0 - a0, da) / safe  # along b's edge
    crossing = ~parallel & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    crossings = (a0 + t[..., None] * da).reshape(len(a), 16, 2)
    candidates = torch.cat([ca, cb, crossings], dim=1)  # (P, 24, 2)
    valid = torch.cat([inside(ca, cb), inside(cb, ca), crossing.reshape(len(a), 16)], dim=1)
    count = valid.sum(dim=1)  # (P,)
    weights = valid.to(candidates.dtype)[..., None]
    centroid = (candidates * weights).sum(dim=1) / count.clamp(min=1)[:, None]  # (P, 2)
    offset = candidates - centroid[:, None]
    angle = torch.atan2(offset[..., 1], offset[..., 0])
    angle = torch.where(valid, angle, torch.full_like(angle, 10.0))  # the invalid ones last
    order = angle.argsort(dim=1)
    ordered = offset.gather(1, order[..., None].expand(-1, -1, 2))  # (P, 24, 2)
    ordered_valid = valid.gather(1, order)
    # an invalid slot repeats the first vertex: it closes the polygon and adds no area
    ordered = torch.where(ordered_valid[..., None], ordered, ordered[:, :1])
    area = 0.5 * cross(ordered, torch.roll(ordered, -1, dims=1)).sum(dim=1).abs()
    area = torch.where(count >= 3, area, torch.zeros_like(area))
    return torch.minimum(area, torch.minimum(a[:, 3] * a[:, 4], b[:, 3] * b[:, 4]))


def ratio(intersection: torch.Tensor, size_a: torch.Tensor, size_b: torch.Tensor) -> torch.Tensor:
    union = size_a + size_b - intersection
    safe = torch.where(union > 0, union, torch.ones_like(union))
    return torch.where(union > 0, intersection / safe, torch.zeros_like(union)).clamp(0.0, 1.0)


def height_overlap(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    top = torch.minimum(a[:, 2] + a[:, 5] / 2, b[:, 2] + b[:, 5] / 2)
    bottom = torch.maximum(a[:, 2] - a[:, 5] / 2, b[:, 2] - b[:, 5] / 2)
    return (top - bottom).clamp(min=0.0)


def bev_iou_pairs(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Rotated BEV IoU (N,) float64 of row-wise pairs a[i], b[i] (N, 7); 0 for empty unions."""
    a, b = a.double().reshape(-1, 7), b.double().reshape(-1, 7)
    iou = ratio(bev_intersection_pairs(a, b), a[:, 3] * a[:, 4], b[:, 3] * b[:, 4])
    identical = (a == b).all(dim=1) & (a[:, 3] * a[:, 4] > 0)
    return torch.where(identical, torch.ones_like(iou), iou)


def iou_3d_pairs(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """3D IoU (N,) float64 of row-wise pairs: BEV intersection x height overlap over the union."""
    a, b = a.double().reshape(-1, 7), b.double().reshape(-1, 7)
    intersection = bev_intersection_pairs(a, b) * height_overlap(a, b)
    volume_a, volume_b = a[:, 3] * a[:, 4] * a[:, 5], b[:, 3] * b[:, 4] * b[:, 5]
    iou = ratio(intersection, volume_a, volume_b)
    identical = (a == b).all(dim=1) & (volume_a > 0)
    return torch.where(identical, torch.ones_like(iou), iou)


def pairwise(a: torch.Tensor, b: torch.Tensor, pairs_fn) -> torch.Tensor:
    """(N, M) float64 of `pairs_fn` over every pair of a (N, 7) x b (M, 7), in blocks of rows."""
    a, b = a.double().reshape(-1, 7), b.double().reshape(-1, 7)
    out = torch.zeros(len(a), len(b), dtype=torch.float64, device=a.device)
    if len(a) == 0 or len(b) == 0:
        return out
    rows = max(1, PAIR_BLOCK // len(b))
    for start in range(0, len(a), rows):
        block = a[start : start + rows]  # (n, 7)
        left = block[:, None].expand(-1, len(b), -1).reshape(-1, 7)
        right = b[None].expand(len(block), -1, -1).reshape(-1, 7)
        out[start : start + rows] = pairs_fn(left, right).reshape(len(block), len(b))
    return out


def bev_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pairwise rotated BEV IoU (N, M) float64 of boxes a (N, 7) and b (M, 7)."""
    return pairwise(a, b, bev_iou_pairs)


def iou_3d(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pairwise 3D IoU (N, M) float64 of boxes a (N, 7) and b (M, 7) (yaw about z only)."""
    return pairwise(a, b, iou_3d_pairs)


def nms_bev(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy BEV non-maximum suppression, as geometry.nms_bev: kept indices (K,) int64 by
    descending score (ties: the earlier index first); a box is suppressed by a kept
    higher-scoring one with BEV IoU > iou_threshold. The IoUs are computed where the boxes are;
    only the (K, K) suppression mask comes to the host, once, for the greedy pass."""
    import numpy as np

    scores = scores.reshape(-1)
    if len(scores) != len(boxes):
        raise ValueError(f"{len(scores)} scores for {len(boxes)} boxes")
    if len(boxes) == 0:
        return torch.zeros(0, dtype=torch.int64, device=boxes.device)
    order = torch.from_numpy(
        np.argsort(-scores.double().cpu().numpy(), kind="stable")  # geometry's tie order
    ).to(boxes.device)
    ranked = boxes.double()[order]
    overlap = (bev_iou(ranked, ranked) > iou_threshold).triu(diagonal=1).cpu().numpy()
    suppressed = np.zeros(len(ranked), dtype=bool)
    kept = []
    for rank in range(len(ranked)):
        if not suppressed[rank]:
            kept.append(rank)
            suppressed |= overlap[rank]
    return order[torch.as_tensor(kept, dtype=torch.int64, device=boxes.device)]
