"""Training targets and losses of the CenterPoint heads (heatmap, box regression, IoU score).

Boxes here are in the ground frame (see config.py). The head grid has h rows (y) and w columns (x)
of `config.cell_m` metres. Regression vector per object (8,): offset x, offset y (cell fractions),
z (m), log l, log w, log h, sin 2yaw, cos 2yaw; with a direction classifier, the bin of the full
heading at each regressing cell (direction.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from dali_cli.detector.config import DetectorConfig
from dali_cli.detector.direction import apply_direction, direction_bin
from dali_cli.detector.distributed import global_normalizer
from dali_cli.geometry import iou_3d, iou_3d_pairs

REGRESSION = ("offset", "z", "size", "rot")  # head maps concatenated in this order -> 8 channels


@dataclass
class Targets:
    """Batched targets. heatmap (B, 1, h, w) float32; index (B, K) int64 flat cell; mask (B, K)
    bool; regression (B, K, 8) float32 relative to that cell; boxes (B, K, 7) float64 ground truth
    (for the IoU target); weight (B, K) float32 (1 at an object's centre cell, less around it);
    direction (B, K) int64, the direction bin of the object's full heading.

    With `config.regression_radius_cells` r > 0 each object supervises the (2r+1)^2 cells around
    its centre cell (a cell near two objects belongs to the nearer centre), so K is up to
    max_objects * (2r+1)^2."""

    heatmap: torch.Tensor
    index: torch.Tensor
    mask: torch.Tensor
    regression: torch.Tensor
    boxes: np.ndarray
    weight: torch.Tensor
    objects: list[np.ndarray] | None = None  # per frame (M_b, 7) float64: every target box
    direction: torch.Tensor | None = None

    def to(self, device: torch.device) -> Targets:
        """The tensors on `device` (boxes and objects stay numpy: they feed the IoU targets)."""
        return Targets(
            self.heatmap.to(device),
            self.index.to(device),
            self.mask.to(device),
            self.regression.to(device),
            self.boxes,
            self.weight.to(device),
            self.objects,
            None if self.direction is None else self.direction.to(device),
        )


def gaussian_radius(
    length_cells: np.ndarray, width_cells: np.ndarray, min_overlap: float
) -> np.ndarray:
    """CenterNet's radius (cells) such that a center shifted by it keeps IoU >= min_overlap; (N,)."""
    a, b = length_cells, width_cells
    r1 = (b + a - np.sqrt((b + a) ** 2 - 4 * a * b * (1 - min_overlap) / (1 + min_overlap))) / 2
    r2 = (2 * (b + a) - np.sqrt(4 * (b + a) ** 2 - 16 * (1 - min_overlap) * a * b)) / 4
    r3 = (
        -2 * min_overlap * (b + a)
        + np.sqrt((2 * min_overlap * (b + a)) ** 2 - 16 * min_overlap * (min_overlap - 1) * a * b)
    ) / 4
    return np.minimum(np.minimum(r1, r2), r3)


def box_cells(
    boxes: np.ndarray, config: DetectorConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Head-grid position of box centers: col (N,) float64, row (N,) float64, inside (N,) bool."""
    h, w = config.head_size
    col = (boxes[:, 0] - config.x_range_m[0]) / config.cell_m
    row = (boxes[:, 1] - config.y_range_m[0]) / config.cell_m
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    inside &= (boxes[:, 2] >= config.z_range_m[0]) & (boxes[:, 2] < config.z_range_m[1])
    return col, row, inside


def regression_cells(
    col: np.ndarray, row: np.ndarray, config: DetectorConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cells that regress each object: object (C,) int64, cell col (C,), row (C,) int64, and
    weight (C,) float64 = exp(-d^2 / 2) of the cell's offset d (cells) from the centre cell.

    col, row (N,) float64: object centres on the head grid. The (2r+1)^2 window around each centre
    cell, cut to the grid; a cell claimed by several objects goes to the one whose centre is nearest.
    """
    h, w = config.head_size
    r = config.regression_radius_cells
    steps = np.arange(-r, r + 1)
    d_row, d_col = (a.ravel() for a in np.meshgrid(steps, steps, indexing="ij"))  # (S,)
    ci, ri = np.floor(col).astype(np.int64), np.floor(row).astype(np.int64)  # (N,)
    cell_col = (ci[:, None] + d_col[None, :]).ravel()  # (N*S,)
    cell_row = (ri[:, None] + d_row[None, :]).ravel()
    obj = np.repeat(np.arange(len(col)), len(steps) ** 2)
    weight = np.tile(np.exp(-(d_row**2 + d_col**2) / 2.0), len(col))
    inside = (cell_col >= 0) & (cell_col < w) & (cell_row >= 0) & (cell_row < h)
    obj, cell_col, cell_row, weight = (
        obj[inside],
        cell_col[inside],
        cell_row[inside],
        weight[inside],
    )
    distance = np.hypot(cell_col + 0.5 - col[obj], cell_row + 0.5 - row[obj])
    order = np.lexsort((distance, cell_row * w + cell_col))  # by cell, nearest centre first
    first = np.ones(len(order), bool)
    flat = (cell_row * w + cell_col)[order]
    first[1:] = flat[1:] != flat[:-1]
    keep = np.sort(order[first])  # back to object-major order
    return obj[keep], cell_col[keep], cell_row[keep], weight[keep]


def build_targets(boxes_list: list[np.ndarray], config: DetectorConfig) -> Targets:
    """Targets for B frames; boxes_list[b] is (M_b, 7) float64 in the ground frame."""
    h, w = config.head_size
    batch = len(boxes_list)
    k = config.max_objects * (2 * config.regression_radius_cells + 1) ** 2
    heatmap = np.zeros((batch, 1, h, w), np.float32)
    index = np.zeros((batch, k), np.int64)
    mask = np.zeros((batch, k), bool)
    regression = np.zeros((batch, k, 8), np.float32)
    gt = np.zeros((batch, k, 7), np.float64)
    weight = np.zeros((batch, k), np.float32)
    direction = np.zeros((batch, k), np.int64)
    objects = []
    rows_grid, cols_grid = np.arange(h)[:, None], np.arange(w)[None, :]
    for b, boxes in enumerate(boxes_list):
        boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
        col, row, inside = box_cells(boxes, config)
        boxes = boxes[inside][: config.max_objects]
        objects.append(boxes)
        col, row = col[inside][: config.max_objects], row[inside][: config.max_objects]
        radius = gaussian_radius(
            boxes[:, 3] / config.cell_m, boxes[:, 4] / config.cell_m, config.min_gaussian_overlap
        )
        radius = np.maximum(config.min_radius_cells, np.floor(radius)).astype(int)
        ci, ri = np.floor(col).astype(int), np.floor(row).astype(int)
        for j in range(len(boxes)):  # loops over objects (tens), each a small window
            r = radius[j]
            sigma = (2 * r + 1) / 6
            r0, r1 = max(ri[j] - r, 0), min(ri[j] + r + 1, h)
            c0, c1 = max(ci[j] - r, 0), min(ci[j] + r + 1, w)
            g = np.exp(
                -((rows_grid[r0:r1] - ri[j]) ** 2 + (cols_grid[:, c0:c1] - ci[j]) ** 2)
                / (2 * sigma**2)
            )
            np.maximum(heatmap[b, 0, r0:r1, c0:c1], g, out=heatmap[b, 0, r0:r1, c0:c1])
        obj, cell_col, cell_row, cell_weight = regression_cells(col, row, config)
        n = len(obj)
        index[b, :n] = cell_row * w + cell_col
        mask[b, :n] = True
        weight[b, :n] = cell_weight
        chosen = boxes[obj]
        regression[b, :n] = np.stack(
            [
                col[obj] - cell_col,
                row[obj] - cell_row,
                chosen[:, 2],
                np.log(np.maximum(chosen[:, 3], 1e-3)),
                np.log(np.maximum(chosen[:, 4], 1e-3)),
                np.log(np.maximum(chosen[:, 5], 1e-3)),
                np.sin(2 * chosen[:, 6]),
                np.cos(2 * chosen[:, 6]),
            ],
            axis=1,
        )
        gt[b, :n] = chosen
        direction[b, :n] = direction_bin(chosen[:, 6], config.direction_offset)
    return Targets(
        torch.from_numpy(heatmap),
        torch.from_numpy(index),
        torch.from_numpy(mask),
        torch.from_numpy(regression),
        gt,
        torch.from_numpy(weight),
        objects,
        torch.from_numpy(direction),
    )


def regression_to_boxes(
    regression: torch.Tensor, index: torch.Tensor, config: DetectorConfig
) -> torch.Tensor:
    """Decode (..., 8) regressions at flat cells (...) into (..., 7) boxes (ground frame)."""
    w = config.head_size[1]
    col = (index % w).to(regression.dtype) + regression[..., 0]
    row = torch.div(index, w, rounding_mode="floor").to(regression.dtype) + regression[..., 1]
    x = config.x_range_m[0] + col * config.cell_m
    y = config.y_range_m[0] + row * config.cell_m
    size = regression[..., 3:6].clamp(-5, 5).exp()  # (..., 3)
    yaw = torch.atan2(regression[..., 6], regression[..., 7]) / 2  # in [-pi/2, pi/2]
    return torch.cat(
        [x[..., None], y[..., None], regression[..., 2:3], size, yaw[..., None]], dim=-1
    )


def focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss on (B, 1, h, w) logits vs Gaussian targets, over
    the number of positive cells of the (global, under DDP) batch."""
    prob = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    positive = target.eq(1).float()
    negative_weight = (1 - target).pow(4)
    positive_loss = torch.log(prob) * (1 - prob).pow(2) * positive
    negative_loss = torch.log(1 - prob) * prob.pow(2) * negative_weight * (1 - positive)
    count = global_normalizer(positive.sum(), 1.0)
    return -(positive_loss.sum() + negative_loss.sum()) / count


def gather_cells(maps: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """maps (B, C, h, w), index (B, K) -> (B, K, C)."""
    batch, channels = maps.shape[:2]
    flat = maps.reshape(batch, channels, -1)  # (B, C, h*w)
    return flat.gather(2, index[:, None, :].expand(-1, channels, -1)).transpose(1, 2)  # (B, K, C)


def peaks_and_boxes(
    maps: dict[str, torch.Tensor], config: DetectorConfig, count: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The `count` strongest 3x3 heatmap peaks of each frame: their heat (B, k), flat cells
    (B, k) and the boxes decoded there, (B, k, 7) float64 ground frame; detached, no threshold,
    no NMS (decoding and the peak losses both start here). With a "dir" map the boxes' yaws are
    full headings in [-pi, pi) (the axis's end in the stronger bin), else in [-pi/2, pi/2]."""
    heat = torch.sigmoid(maps["heatmap"].detach())  # (B, 1, h, w)
    peaks = heat * (F.max_pool2d(heat, 3, stride=1, padding=1) == heat)
    batch = heat.shape[0]
    k = min(count, peaks[0].numel())
    heat_score, index = peaks.reshape(batch, -1).topk(k, dim=1)  # (B, k), (B, k)
    regression_maps = torch.cat([maps[name].detach() for name in REGRESSION], dim=1)
    boxes = regression_to_boxes(gather_cells(regression_maps, index).double(), index, config)
    if "dir" in maps:
        bins = gather_cells(maps["dir"].detach(), index).argmax(dim=-1)  # (B, k)
        boxes[..., 6] = apply_direction(boxes[..., 6], bins, config.direction_offset)
    return heat_score, index, boxes


def peak_boxes(
    maps: dict[str, torch.Tensor], config: DetectorConfig, count: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """`peaks_and_boxes` without the heat: flat cells (B, k) and boxes (B, k, 7)."""
    _, index, boxes = peaks_and_boxes(maps, config, count)
    return index, boxes


def peak_iou_loss(
    maps: dict[str, torch.Tensor], targets: Targets, config: DetectorConfig
) -> torch.Tensor:
    """BCE of the IoU head at the `config.iou_peak_cells` strongest heatmap peaks of each frame
    (what decoding will score), against the best 3D IoU of the box decoded there with any target
    box (0 on background). Without it the IoU head is trained only at object centres and says
    anything elsewhere, so a score that leans on it (iou_alpha) lifts background peaks."""
    index, boxes = peak_boxes(maps, config, config.iou_peak_cells)
    batch, k = index.shape
    if boxes.is_cuda:  # on the GPU: the host does not wait
        target = device_peak_targets(boxes, targets.objects, batch, k)
        logits = gather_cells(maps["iou"], index)[..., 0]  # (B, k)
        losses = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
        return losses.sum() / global_normalizer(logits.new_tensor(float(losses.numel())), 1.0)
    boxes = boxes.cpu().numpy()  # (B, k, 7): the exact IoU targets are numpy geometry
    target = np.zeros((batch, k), np.float32)
    for b in range(batch):  # frames: one or a few per batch
        objects = targets.objects[b] if targets.objects is not None else np.zeros((0, 7))
        if len(objects):
            target[b] = iou_3d(boxes[b], objects).max(axis=1)
    logits = gather_cells(maps["iou"], index)[..., 0]  # (B, k)
    losses = F.binary_cross_entropy_with_logits(
        logits, torch.from_numpy(target).to(logits.device), reduction="none"
    )
    return losses.sum() / global_normalizer(logits.new_tensor(float(losses.numel())), 1.0)


def device_peak_targets(boxes: torch.Tensor, objects, batch: int, k: int) -> torch.Tensor:
    """(B, k) float32 on boxes' device: the best 3D IoU of each peak's box (B, k, 7) with frame
    b's target boxes objects[b] (M_b, 7) (0 without any), computed there (box_ops)."""
    from dali_cli.detector import box_ops

    target = torch.zeros(batch, k, dtype=torch.float32, device=boxes.device)
    for b in range(batch):  # frames: one or a few per batch
        if objects is not None and len(objects[b]):
            found = torch.from_numpy(objects[b]).to(boxes.device, non_blocking=True)
            target[b] = box_ops.iou_3d(boxes[b], found).max(dim=1).values.float()
    return target


def cell_iou_targets(
    predicted_boxes: torch.Tensor,
    targets: Targets,
    mask: torch.Tensor,
    on_device: bool | None = None,
) -> torch.Tensor:
    """(B, K) float32 IoU-head targets: the 3D IoU of the box decoded at each regressing cell
    (B, K, 7) with its object, 0 elsewhere. `on_device` (default: on a GPU): computed where the
    boxes are for every cell (box_ops, no host copy); else numpy geometry on the selected cells
    (one copy to the host)."""
    if predicted_boxes.is_cuda if on_device is None else on_device:
        from dali_cli.detector import box_ops

        gt = torch.from_numpy(targets.boxes).to(predicted_boxes.device, non_blocking=True)
        iou = box_ops.iou_3d_pairs(predicted_boxes.reshape(-1, 7), gt.reshape(-1, 7))
        return iou.reshape(mask.shape).float() * mask
    iou_target = np.zeros(mask.shape, np.float32)
    selected = mask.cpu().numpy()
    if selected.any():  # exact rotated-box IoU (numpy geometry): one copy to the host
        iou_target[selected] = iou_3d_pairs(
            predicted_boxes.cpu().numpy()[selected], targets.boxes[selected]
        )
    return torch.from_numpy(iou_target).to(mask.device)


def detection_loss(
    maps: dict[str, torch.Tensor],
    targets: Targets,
    config: DetectorConfig,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss and its terms (detached () tensors, for the log: no host copy per step).
    Every term is a mean over the global batch (see distributed.global_normalizer). The IoU head learns the 3D IoU of the box
    decoded at each regressing cell with its object (a soft BCE target), weighted like the box loss."""
    heat = focal_loss(maps["heatmap"], targets.heatmap)
    regression_maps = torch.cat([maps[name] for name in REGRESSION], dim=1)  # (B, 8, h, w)
    predicted = gather_cells(regression_maps, targets.index)  # (B, K, 8)
    mask = targets.mask  # (B, K)
    cell_weight = targets.weight * mask  # (B, K)
    count = global_normalizer(cell_weight.sum(), 1e-6)
    weights = predicted.new_tensor(config.regression_weights)  # (8,)
    l1 = F.l1_loss(predicted, targets.regression, reduction="none") * weights  # (B, K, 8)
    box = (l1 * cell_weight[..., None]).sum() / count
    iou_logits = gather_cells(maps["iou"], targets.index)[..., 0]  # (B, K)
    with torch.no_grad():
        predicted_boxes = regression_to_boxes(predicted.detach().double(), targets.index, config)
        iou_target = cell_iou_targets(predicted_boxes, targets, mask)  # (B, K)
    iou = (
        F.binary_cross_entropy_with_logits(iou_logits, iou_target, reduction="none") * cell_weight
    ).sum() / count
    w_heat, w_box, w_iou = config.loss_weights
    total = w_heat * heat + w_box * box + w_iou * iou
    terms = {"loss": total, "heatmap": heat, "box": box, "iou": iou}
    if "dir" in maps:  # cross-entropy of the direction bins, weighted like the box loss
        logits = gather_cells(maps["dir"], targets.index)  # (B, K, 2)
        entropy = F.cross_entropy(
            logits.reshape(-1, logits.shape[-1]), targets.direction.reshape(-1), reduction="none"
        ).reshape(mask.shape)  # (B, K)
        direction = (entropy * cell_weight).sum() / count
        total = total + config.direction_weight * direction
        terms.update(loss=total, direction=direction)
    if config.iou_peak_cells > 0:
        peak = peak_iou_loss(maps, targets, config)
        total = total + w_iou * peak
        terms.update(loss=total, iou_peaks=peak)
    return total, {name: value.detach() for name, value in terms.items()}
