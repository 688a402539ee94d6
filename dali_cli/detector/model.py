"""The detector network: pillar encoder -> multi-scale BEV backbone -> CenterPoint heads.

Plain torch, no custom ops. Shapes: B frames, P points (all frames concatenated), V non-empty
pillars, C channels, H x W the pillar grid (rows along y, columns along x), h x w the head grid
(stride 2). A documented deviation from the paper's SECOND-IoU (see docs/method.md).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from dali_cli.detector.config import DetectorConfig
from dali_cli.detector.refine import BoxRefiner

# head name -> output channels; "rot" is (sin 2yaw, cos 2yaw), the heading axis (a car turned by
# 180 deg is the same box), "dir" the two direction bins' logits that pick its front (direction.py)
HEADS = {"heatmap": 1, "offset": 2, "z": 1, "size": 3, "rot": 2, "iou": 1}
DIRECTION_HEAD = {"dir": 2}


def heads(config: DetectorConfig) -> dict[str, int]:
    """The head maps a detector of `config` outputs: HEADS, and "dir" with a direction classifier."""
    return {**HEADS, **(DIRECTION_HEAD if config.direction else {})}


def pillarize(points: torch.Tensor, batch_index: torch.Tensor, config: DetectorConfig):
    """Assign points to pillars and build the per-point PFN input.

    points: (P, 4) float32 x, y, z, intensity in the sensor frame; batch_index: (P,) int64.
    Returns features (P', D) float32, pillar_of_point (P',) int64 into the V unique pillars,
    pillar_cell (V,) int64 flat index b * H * W + row * W + col. Points outside the range are dropped.
    """
    rows, cols = config.grid_size
    (x0, x1), (y0, y1), (z0, z1) = config.x_range_m, config.y_range_m, config.z_range_m
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    keep = (x >= x0) & (x < x1) & (y >= y0) & (y < y1) & (z >= z0) & (z < z1)
    points, batch_index = points[keep], batch_index[keep]  # (P', 4), (P',)
    col = ((points[:, 0] - x0) / config.pillar_m).long().clamp_(0, cols - 1)  # (P',)
    row = ((points[:, 1] - y0) / config.pillar_m).long().clamp_(0, rows - 1)  # (P',)
    cell = (batch_index * rows + row) * cols + col  # (P',)
    pillar_cell, pillar_of_point = torch.unique(cell, return_inverse=True)  # (V,), (P',)
    count = torch.zeros(len(pillar_cell), device=points.device).index_add_(
        0, pillar_of_point, torch.ones_like(points[:, 0])
    )  # (V,)
    xyz = points[:, :3]  # (P', 3)
    mean = torch.zeros(len(pillar_cell), 3, device=points.device).index_add_(
        0, pillar_of_point, xyz
    )
    mean = mean / count[:, None]  # (V, 3)
    center_x = x0 + (col.float() + 0.5) * config.pillar_m  # (P',)
    center_y = y0 + (row.float() + 0.5) * config.pillar_m  # (P',)
    parts = [
        xyz,
        xyz - mean[pillar_of_point],
        (xyz[:, 0] - center_x)[:, None],
        (xyz[:, 1] - center_y)[:, None],
    ]
    if config.features == "xyzi":
        parts.append(points[:, 3:4])
    return torch.cat(parts, dim=1), pillar_of_point, pillar_cell  # (P', 8 or 9)


class PillarEncoder(nn.Module):
    """PointPillars PFN: a shared linear layer per point, then max over each pillar's points."""

    def __init__(self, config: DetectorConfig):
        super().__init__()
        self.config = config
        in_dims = 8 + (1 if config.features == "xyzi" else 0)
        self.linear = nn.Linear(in_dims, config.pfn_channels, bias=False)
        self.norm = nn.BatchNorm1d(config.pfn_channels)

    def forward(
        self,
        points: torch.Tensor,
        batch_index: torch.Tensor,
        batch_size: int,
        grid: DetectorConfig | None = None,
    ):
        """points (P, 4), batch_index (P,) -> BEV canvas (B, C, H, W) of `grid`'s ranges (default:
        the trained config; the weights do not depend on the grid's extent)."""
        grid = grid or self.config
        rows, cols = grid.grid_size
        channels = self.config.pfn_channels
        features, pillar_of_point, pillar_cell = pillarize(points, batch_index, grid)
        features = F.relu(self.norm(self.linear(features)))  # (P', C)
        pillars = torch.zeros(
            len(pillar_cell), channels, dtype=features.dtype, device=features.device
        )
        index = pillar_of_point[:, None].expand(-1, channels)  # (P', C)
        pillars = pillars.scatter_reduce(
            0, index, features, reduce="amax", include_self=False
        )  # (V, C)
        canvas = torch.zeros(
            batch_size * rows * cols, channels, dtype=pillars.dtype, device=pillars.device
        )
        canvas[pillar_cell] = pillars  # (B*H*W, C)
        return canvas.view(batch_size, rows, cols, channels).permute(0, 3, 1, 2)  # (B, C, H, W)


def conv_bn(in_channels: int, out_channels: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.ReLU(inplace=True),
    )


class Backbone(nn.Module):
    """Three strided blocks (strides 2, 4, 8), each upsampled to stride 2 and concatenated."""

    def __init__(self, config: DetectorConfig):
        super().__init__()
        widths = (config.pfn_channels, *config.block_channels)
        self.blocks = nn.ModuleList()
        self.ups = nn.ModuleList()
        for level, (layers, c_in, c_out) in enumerate(
            zip(config.block_layers, widths[:-1], widths[1:], strict=True)
        ):
            convs = [conv_bn(c_in, c_out, stride=2)] + [
                conv_bn(c_out, c_out) for _ in range(layers)
            ]
            self.blocks.append(nn.Sequential(*convs))
            factor = 2**level  # this block's stride relative to the head's stride 2
            up = (
                nn.Conv2d(c_out, config.up_channels, 1, bias=False)
                if factor == 1
                else nn.ConvTranspose2d(
                    c_out, config.up_channels, factor, stride=factor, bias=False
                )
            )
            self.ups.append(
                nn.Sequential(up, nn.BatchNorm2d(config.up_channels), nn.ReLU(inplace=True))
            )

    def forward(self, canvas: torch.Tensor) -> torch.Tensor:
        """canvas (B, C, H, W) -> fused features (B, 3 * up_channels, H/2, W/2)."""
        x, fused = canvas, []
        for block, up in zip(self.blocks, self.ups, strict=True):
            x = block(x)  # (B, C_l, H / 2^(l+1), W / 2^(l+1))
            fused.append(up(x))  # (B, up_channels, H/2, W/2)
        return torch.cat(fused, dim=1)


class CenterHead(nn.Module):
    """A shared 3x3 conv, then one 1x1 conv per output (see `heads`)."""

    def __init__(self, config: DetectorConfig):
        super().__init__()
        self.shared = conv_bn(3 * config.up_channels, config.head_channels)
        self.outputs = nn.ModuleDict(
            {name: nn.Conv2d(config.head_channels, dims, 1) for name, dims in heads(config).items()}
        )
        nn.init.constant_(self.outputs["heatmap"].bias, -2.19)  # prior p = 0.1 (CenterNet)

    def forward(self, features: torch.Tensor) -> dict[str, torch.Tensor]:
        shared = self.shared(features)  # (B, head_channels, h, w)
        return {
            name: conv(shared) for name, conv in self.outputs.items()
        }  # name -> (B, dims, h, w)


class PillarCenterNet(nn.Module):
    """points -> dict of head maps, each (B, dims, h, w) float32 (raw logits/regressions)."""

    def __init__(self, config: DetectorConfig):
        super().__init__()
        self.config = config
        self.encoder = PillarEncoder(config)
        self.backbone = Backbone(config)
        self.head = CenterHead(config)
        self.refiner = BoxRefiner(config) if config.refine else None

    def forward(
        self,
        points: torch.Tensor,
        batch_index: torch.Tensor,
        batch_size: int,
        grid: DetectorConfig | None = None,
    ):
        """`grid`: a config with other x/y ranges (same pillar size) to run on, e.g. a larger area."""
        canvas = self.encoder(points, batch_index, batch_size, grid)  # (B, C, H, W)
        maps = self.head(self.backbone(canvas))
        return {name: value.float() for name, value in maps.items()}
