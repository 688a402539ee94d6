"""Second stage: refine each first-stage box from the raw points around it (LiDAR R-CNN style).

The BEV heads see the scene through 0.32 m pillars and a max over each pillar's points, which is
enough to find cars but loses the exact roof, bottom and sides that a 3D IoU of 0.7 needs. The
refiner looks again at the points themselves: for each proposal it takes up to `refine_points`
points inside the box grown by `refine_margin_m` (ground points under the car included, so the
bottom is visible), expresses them in the proposal's frame, runs a small PointNet and predicts a
residual box and the 3D IoU of the refined box (the score's IoU factor).

Shapes: K proposals, N points per proposal, D = 9 point features (local x, y, z and the distances
to the six faces, metres; the network adds the same six over the half sizes). Boxes (K, 7) in the
ground frame. The residual's heading is a turn of less than pi/2 about the proposal's; with a
direction classifier (config.direction) an eighth output, the flip logit, says whether the car's
front lies at the other end of the refined box's axis (the points in the box frame show it: the
windscreen, the taper of the bonnet, the ends' depths), so a refined box faces any way.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from dali_cli.detector import box_ops
from dali_cli.detector.config import DetectorConfig
from dali_cli.geometry import bev_iou, iou_3d, point_box_pairs, wrap_angle

POINT_FEATURES = 9
CROP_PAIR_BLOCK = 1 << 22  # point-box pairs per block of the torch crop (~150 MB of temporaries)
CROP_CELL_M = 1.0  # cell of the coarse grid that crops a frame's points to the proposals' areas
PROPOSAL_SIZE_M = (0.2, 8.0)  # proposals' l, w, h are clipped to this before refinement: an
# untrained head's boxes can be 100 m long and would gather every point of the frame


def wrap_half_turn(angle: np.ndarray | torch.Tensor):
    """Angles (radians) wrapped to [-pi/2, pi/2): a box turned by pi is the same box."""
    return (angle + np.pi / 2) % np.pi - np.pi / 2


def near_boxes(points: np.ndarray, boxes: np.ndarray, margin_m: float) -> np.ndarray:
    """Indices (P',) of the points (P, >=2) whose 1 m BEV cell lies within reach of some box.

    A coarse pre-filter before the exact containment test: one integer lookup per point instead of
    a candidate search over the whole frame."""
    if len(points) == 0 or len(boxes) == 0:
        return np.zeros(0, np.int64)
    reach = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4]) + margin_m + CROP_CELL_M  # (K,)
    low = np.floor((boxes[:, :2] - reach[:, None]) / CROP_CELL_M).astype(np.int64)  # (K, 2)
    high = np.floor((boxes[:, :2] + reach[:, None]) / CROP_CELL_M).astype(np.int64)
    origin = low.min(axis=0)
    shape = high.max(axis=0) - origin + 1
    grid = np.zeros(shape, bool)
    for k in range(len(boxes)):  # boxes: tens; each marks a small block
        grid[low[k, 0] - origin[0] : high[k, 0] - origin[0] + 1,
             low[k, 1] - origin[1] : high[k, 1] - origin[1] + 1] = True  # fmt: skip
    cell = np.floor(np.asarray(points[:, :2], np.float64) / CROP_CELL_M).astype(np.int64) - origin
    inside = np.all((cell >= 0) & (cell < shape), axis=1)
    candidates = np.flatnonzero(inside)
    return candidates[grid[cell[candidates, 0], cell[candidates, 1]]]


def box_point_features(
    points: np.ndarray, boxes: np.ndarray, count: int, margin_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Point features of each proposal: (K, count, 9) float32 and the points found (K,) int64.

    points (P, >=3) ground frame; boxes (K, 7). The points inside each box grown by `margin_m` are
    subsampled at evenly spaced positions of their (scan) order, repeated when fewer than `count`
    (deterministic: no random draw). Features: x, y, z in the box frame, then the distances to
    the faces at -l/2, -w/2, -h/2 (local + half size) and at +l/2, +w/2, +h/2 (half size - local),
    negative outside. A box without points gets zeros.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    features = np.zeros((len(boxes), count, POINT_FEATURES), np.float32)
    found = np.zeros(len(boxes), np.int64)
    if len(boxes) == 0 or len(points) == 0:
        return features, found
    near = near_boxes(points, boxes, margin_m)
    point_index, box_index = point_box_pairs(points[near, :3], boxes, margin_m)
    if len(point_index) == 0:
        return features, found
    order = np.argsort(box_index, kind="stable")
    point_index, box_index = near[point_index[order]], box_index[order]
    found = np.bincount(box_index, minlength=len(boxes)).astype(np.int64)
    start = np.cumsum(found) - found  # (K,)
    has = np.flatnonzero(found > 0)
    slots = (np.arange(count) + 0.5) / count  # (N,)
    pick = start[has, None] + np.floor(slots[None, :] * found[has, None]).astype(np.int64)
    chosen = np.asarray(points[point_index[pick], :3], np.float64)  # (K', N, 3)
    box = boxes[has]
    offset = chosen - box[:, None, :3]
    c, s = np.cos(box[:, 6])[:, None], np.sin(box[:, 6])[:, None]
    local = np.stack(
        [
            c * offset[..., 0] + s * offset[..., 1],
            -s * offset[..., 0] + c * offset[..., 1],
            offset[..., 2],
        ],
        axis=-1,
    )  # (K', N, 3)
    half = box[:, None, 3:6] / 2  # (K', 1, 3)
    faces = np.concatenate([local + half, half - local], axis=-1)  # (K', N, 6)
    features[has] = np.concatenate([local, faces], axis=-1).astype(np.float32)
    return features, found


def box_point_features_torch(
    points: torch.Tensor, boxes: torch.Tensor, count: int, margin_m: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """`box_point_features` on torch tensors, on their device: (K, count, 9) float32 features and
    the points found (K,) int64, the same points picked (numpy stays the reference: tests within
    1e-6).

    points (P, >=3), boxes (K, 7). Every point is tested against every box in blocks of about
    CROP_PAIR_BLOCK pairs (no coarse grid: on a GPU the brute-force test is cheaper than building
    one, and no step waits on a data-dependent size); the evenly spaced picks are a search in
    each box's running count of its points, so the order is the numpy version's (scan order).
    """
    device = points.device
    boxes = boxes.to(device, torch.float64).reshape(-1, 7)
    features = torch.zeros(len(boxes), count, POINT_FEATURES, dtype=torch.float32, device=device)
    found = torch.zeros(len(boxes), dtype=torch.int64, device=device)
    if len(boxes) == 0 or len(points) == 0:
        return features, found
    xyz = points[:, :3].double()  # (P, 3)
    slots = (torch.arange(count, dtype=torch.float64, device=device) + 0.5) / count  # (N,)
    rows = max(1, CROP_PAIR_BLOCK // len(xyz))
    for start in range(0, len(boxes), rows):
        box = boxes[start : start + rows]  # (k, 7)
        c, s = torch.cos(box[:, 6:7]), torch.sin(box[:, 6:7])  # (k, 1)
        dx, dy = xyz[None, :, 0] - box[:, 0:1], xyz[None, :, 1] - box[:, 1:2]  # (k, P)
        reach = 0.5 * box[:, 3:6] + margin_m  # (k, 3)
        inside = (c * dx + s * dy).abs() <= reach[:, 0:1]
        inside &= (c * dy - s * dx).abs() <= reach[:, 1:2]
        inside &= (xyz[None, :, 2] - box[:, 2:3]).abs() <= reach[:, 2:3]
        running = inside.cumsum(dim=1)  # (k, P): points of the box up to each point
        total = running[:, -1]  # (k,)
        wanted = torch.floor(slots[None, :] * total[:, None].double()).long() + 1  # (k, N)
        index = torch.searchsorted(running, wanted).clamp_(max=len(xyz) - 1)  # (k, N)
        offset = xyz[index] - box[:, None, :3]  # (k, N, 3)
        local = torch.stack(
            [c * offset[..., 0] + s * offset[..., 1], -s * offset[..., 0] + c * offset[..., 1],
             offset[..., 2]],
            dim=-1,
        )  # fmt: skip
        half = box[:, None, 3:6] / 2  # (k, 1, 3)
        block = torch.cat([local, local + half, half - local], dim=-1).float()  # (k, N, 9)
        features[start : start + rows] = block * (total > 0)[:, None, None]
        found[start : start + rows] = total
    return features, found


def clip_proposals(boxes: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """Proposals (K, 7) float64 with l, w, h clipped to PROPOSAL_SIZE_M (a copy; numpy or torch)."""
    if isinstance(boxes, torch.Tensor):
        boxes = boxes.double().reshape(-1, 7).clone()
        boxes[:, 3:6] = boxes[:, 3:6].clamp(*PROPOSAL_SIZE_M)
        return boxes
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7).copy()
    boxes[:, 3:6] = np.clip(boxes[:, 3:6], *PROPOSAL_SIZE_M)
    return boxes


def encode_residuals(proposals, truth):
    """Regression targets (K, 7) from proposals to their ground truth (both (K, 7)): the centre
    shift in the proposal's frame over its BEV diagonal (x, y) and height (z), log size ratios,
    and the heading difference modulo pi. numpy arrays or torch tensors (then on their device)."""
    xp = torch if isinstance(proposals, torch.Tensor) else np
    offset = truth[:, :3] - proposals[:, :3]
    c, s = xp.cos(proposals[:, 6]), xp.sin(proposals[:, 6])
    diagonal = xp.hypot(proposals[:, 3], proposals[:, 4])
    return xp.stack(
        [
            (c * offset[:, 0] + s * offset[:, 1]) / diagonal,
            (-s * offset[:, 0] + c * offset[:, 1]) / diagonal,
            offset[:, 2] / proposals[:, 5],
            xp.log(truth[:, 3] / proposals[:, 3]),
            xp.log(truth[:, 4] / proposals[:, 4]),
            xp.log(truth[:, 5] / proposals[:, 5]),
            wrap_half_turn(truth[:, 6] - proposals[:, 6]),
        ],
        1,
    )


def flip_targets(proposals, truth):
    """(K,) float: 1 where the true heading points away (more than pi/2) from the proposal's, the
    refiner's flip target (numpy or torch, like `proposals`)."""
    xp = torch if isinstance(proposals, torch.Tensor) else np
    return (xp.cos(truth[:, 6] - proposals[:, 6]) < 0) * 1.0


def apply_residuals(proposals, residuals):
    """The inverse of `encode_residuals`: refined boxes (K, 7), yaw in [-pi, pi) (numpy or torch,
    like `proposals`). Residuals (K, 7), or (K, 8) with a flip logit: where it is positive the
    refined box turns by pi."""
    tensor = isinstance(proposals, torch.Tensor)
    xp = torch if tensor else np
    c, s = xp.cos(proposals[:, 6]), xp.sin(proposals[:, 6])
    diagonal = xp.hypot(proposals[:, 3], proposals[:, 4])
    dx, dy = residuals[:, 0] * diagonal, residuals[:, 1] * diagonal
    refined = proposals.clone() if tensor else proposals.copy()
    refined[:, 0] += c * dx - s * dy
    refined[:, 1] += s * dx + c * dy
    refined[:, 2] += residuals[:, 2] * proposals[:, 5]
    refined[:, 3:6] *= xp.exp(xp.clip(residuals[:, 3:6], -1.0, 1.0))
    yaw = proposals[:, 6] + residuals[:, 6]
    if residuals.shape[1] > 7:
        yaw = yaw + np.pi * (residuals[:, 7] > 0)
    refined[:, 6] = box_ops.wrap_angle(yaw) if tensor else wrap_angle(yaw)
    return refined


class BoxRefiner(nn.Module):
    """PointNet over each proposal's points -> residual (K, 7) and IoU logit (K,).

    No batch norm: a batch is a few dozen boxes whose points repeat (boxes with few points are
    padded by repetition), and on toy scans BN's statistics made the refiner learn slower and its
    IoU head not at all (0.64 vs 0.72 mean refined IoU after 400 steps). Point features are the 9
    metric ones plus the local coordinates and face distances over the half sizes (15)."""

    def __init__(self, config: DetectorConfig):
        super().__init__()
        c = config.refine_channels
        widths = (POINT_FEATURES + 6, c // 2, c, 2 * c)
        self.point_mlp = nn.Sequential(
            *(
                layer
                for a, b in zip(widths[:-1], widths[1:], strict=True)
                for layer in (nn.Linear(a, b), nn.ReLU(inplace=True))
            )
        )
        self.box_mlp = nn.Sequential(
            nn.Linear(2 * c + 3, 2 * c),
            nn.ReLU(inplace=True),
            nn.Linear(2 * c, 2 * c),
            nn.ReLU(inplace=True),
        )
        self.residual = nn.Linear(2 * c, 8 if config.direction else 7)
        self.iou = nn.Linear(2 * c, 1)
        nn.init.zeros_(self.residual.weight)  # start as the identity refinement
        nn.init.zeros_(self.residual.bias)

    def forward(self, features: torch.Tensor, sizes: torch.Tensor):
        """features (K, N, 9), sizes (K, 3) proposal l, w, h -> residuals (K, 7 or 8: with the
        flip logit), IoU logits (K,)."""
        half = sizes[:, None, :] / 2  # (K, 1, 3)
        relative = torch.cat([features[..., :3] / half, features[..., 3:6] / half], dim=-1)
        # the points as one (K N, 15) matrix: the in-place ReLUs then act on whole tensors, not on
        # views of the linear layers' outputs (whose backward copied slices: a third of the
        # refiner's step); the last ReLU after the max, with which it commutes, on 2c values a box
        # instead of N x 2c. Outputs and gradients bit for bit those of the plain stack
        # (tests/test_refine.py).
        x = torch.cat([features, relative], dim=-1).flatten(0, 1)  # (K N, 15)
        x = self.point_mlp[:-1](x).unflatten(0, features.shape[:2])  # (K, N, 2c)
        pooled = torch.relu(x.amax(dim=1))  # (K, 2c)
        hidden = self.box_mlp(torch.cat([pooled, sizes], dim=1))
        # float32 out also under bf16 autocast: the losses and the box decoding stay in float32
        return self.residual(hidden).float(), self.iou(hidden)[:, 0].float()


def refine_boxes(
    refiner: BoxRefiner, points: np.ndarray, proposals: np.ndarray, config: DetectorConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Refined boxes (K, 7) float64 and their predicted 3D IoU (K,) float32, one frame.

    points (P, >=3) and proposals (K, 7) in the network's (ground, PTSN-scaled) frame. With the
    refiner on a GPU the points go there once and are cropped there (box_point_features_torch);
    on the CPU the numpy crop runs (the reference)."""
    if len(proposals) == 0:
        return np.zeros((0, 7)), np.zeros(0, np.float32)
    proposals = clip_proposals(proposals)
    device = next(refiner.parameters()).device
    if device.type == "cpu":
        features, _ = box_point_features(
            points, proposals, config.refine_points, config.refine_margin_m
        )
        features = torch.from_numpy(features)
    else:
        features, _ = box_point_features_torch(
            torch.from_numpy(np.asarray(points[:, :3], np.float32)).to(device),
            torch.from_numpy(proposals).to(device),
            config.refine_points,
            config.refine_margin_m,
        )
    residuals, iou_logits = refiner(
        features.to(device), torch.from_numpy(proposals[:, 3:6].astype(np.float32)).to(device)
    )
    refined = apply_residuals(proposals, residuals.double().cpu().numpy())
    return refined, torch.sigmoid(iou_logits).float().cpu().numpy()


def jitter_boxes(boxes: np.ndarray, rng: np.random.Generator, flip: bool = False) -> np.ndarray:
    """Ground-truth boxes (M, 7) disturbed like first-stage boxes: positives for the refiner
    from the first step on (the heads' own proposals are poor early in training). `flip`: half
    of them, drawn at random, turned by pi as well (the flip logit's negatives and positives)."""
    noisy = boxes.copy()
    m = len(boxes)
    noisy[:, :2] += rng.normal(0.0, 0.3, size=(m, 2))
    noisy[:, 2] += rng.normal(0.0, 0.15, size=m)
    noisy[:, 3:6] *= np.exp(rng.normal(0.0, 0.1, size=(m, 3)))
    noisy[:, 6] += rng.normal(0.0, 0.1, size=m)
    if flip:
        noisy[:, 6] = wrap_angle(noisy[:, 6] + np.pi * (rng.random(m) < 0.5))
    return noisy


def refine_loss(
    refiner: BoxRefiner,
    points_list: list[np.ndarray] | list[torch.Tensor],
    proposals_list: list[np.ndarray] | list[torch.Tensor],
    objects_list: list[np.ndarray],
    config: DetectorConfig,
    rng: np.random.Generator | list[np.random.Generator],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Residual (L1, on proposals with BEV IoU >= 0.4 with a target box, plus, with a direction
    classifier, config.direction_weight x the flip logit's BCE there) and IoU (BCE against
    the refined box's best 3D IoU with any target box) losses over a batch of frames, each a
    mean over the (global, under DDP) batch's positives and proposals.

    points_list[b] (P_b, >=3), proposals_list[b] (K_b, 7) (detached first-stage boxes) and
    objects_list[b] (M_b, 7) target boxes (numpy), all in the ground frame. `rng`: one generator
    for the whole batch, or one per frame (what distributed training needs); the jitter is drawn
    on the host either way. Points and proposals as numpy arrays: crops and targets in numpy (the
    reference); as torch tensors on the refiner's device: crops, IoU and residual targets there
    (torch, box_ops), so that a GPU step never waits for the host."""
    from dali_cli.detector.distributed import global_normalizer

    rngs = rng if isinstance(rng, list) else [rng] * len(points_list)
    device = next(refiner.parameters()).device
    on_device = bool(points_list) and isinstance(points_list[0], torch.Tensor)
    features, sizes, proposals, truth, positive, rows = [], [], [], [], [], []
    for b, (points, found, objects) in enumerate(
        zip(points_list, proposals_list, objects_list, strict=True)
    ):
        found = clip_proposals(found)
        if len(objects):
            jittered = jitter_boxes(objects, rngs[b], flip=config.direction)
            if on_device:
                objects = torch.from_numpy(np.asarray(objects, np.float64)).to(device)
                jittered = torch.from_numpy(jittered).to(device)
                boxes = torch.cat([found, jittered])
            else:
                boxes = np.concatenate([found, jittered])
        else:
            boxes = found
        if len(boxes) == 0:
            continue
        crop = box_point_features_torch if on_device else box_point_features
        frame_features, _ = crop(points, boxes, config.refine_points, config.refine_margin_m)
        features.append(frame_features if on_device else torch.from_numpy(frame_features))
        sizes.append(boxes[:, 3:6])
        proposals.append(boxes)
        first = rows[-1][1].stop if rows else 0
        rows.append((b, slice(first, first + len(boxes)), objects))
        if len(objects) and on_device:
            overlap = box_ops.bev_iou(boxes, objects)  # (K, M)
            best, index = overlap.max(dim=1)
            truth.append(objects[index])
            positive.append(best >= 0.4)
        elif len(objects):
            overlap = bev_iou(boxes, objects)  # (K, M)
            truth.append(objects[overlap.argmax(axis=1)])
            positive.append(overlap.max(axis=1) >= 0.4)
        else:
            truth.append(boxes.clone() if on_device else boxes.copy())
            positive.append(
                torch.zeros(len(boxes), dtype=torch.bool, device=device)
                if on_device
                else np.zeros(len(boxes), bool)
            )
    if not proposals:  # still a graph over every weight: DDP waits for each one's gradient
        zero = sum(p.sum() for p in refiner.parameters()) * 0.0
        global_normalizer(zero.new_zeros(()), 1.0)  # the collectives the other ranks run
        global_normalizer(zero.new_zeros(()), 1.0)
        return zero, zero
    if on_device:
        proposals_all, truth_all = torch.cat(proposals), torch.cat(truth)
        positive_all, sizes_all = torch.cat(positive), torch.cat(sizes).float()
    else:
        proposals_all, truth_all = np.concatenate(proposals), np.concatenate(truth)
        positive_all = torch.from_numpy(np.concatenate(positive)).to(device)
        sizes_all = torch.from_numpy(np.concatenate(sizes).astype(np.float32)).to(device)
    residuals, iou_logits = refiner(torch.cat(features).to(device), sizes_all)
    target = encode_residuals(proposals_all, truth_all)
    target = target.float() if on_device else torch.from_numpy(target.astype(np.float32))
    target = target.to(device)
    l1 = F.l1_loss(residuals[:, :7], target, reduction="none").sum(dim=1)  # (K,)
    if residuals.shape[1] > 7:
        flip = flip_targets(proposals_all, truth_all)
        flip = flip.float() if on_device else torch.from_numpy(flip.astype(np.float32))
        l1 = l1 + config.direction_weight * F.binary_cross_entropy_with_logits(
            residuals[:, 7], flip.to(device), reduction="none"
        )
    box = (l1 * positive_all).sum() / global_normalizer(positive_all.sum().float(), 1.0)
    with torch.no_grad():
        moved = residuals.detach().double()
        refined = apply_residuals(proposals_all, moved if on_device else moved.cpu().numpy())
        if on_device:
            iou_target = torch.zeros(len(refined), dtype=torch.float32, device=device)
            for _, frame_rows, objects in rows:
                if len(objects):
                    best = box_ops.iou_3d(refined[frame_rows], objects).max(dim=1).values
                    iou_target[frame_rows] = best.float()
        else:
            iou_target = np.zeros(len(refined), np.float32)
            for _, frame_rows, objects in rows:
                if len(objects):
                    iou_target[frame_rows] = iou_3d(refined[frame_rows], objects).max(axis=1)
            iou_target = torch.from_numpy(iou_target).to(device)
    losses = F.binary_cross_entropy_with_logits(iou_logits, iou_target, reduction="none")
    return box, losses.sum() / global_normalizer(losses.new_tensor(float(len(losses))), 1.0)
