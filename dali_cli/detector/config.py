"""The detector's hyper-parameters in one dataclass, saved with every checkpoint (model.json)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

# fields earlier models' model.json carry, with the one value still read: a second refinement
# pass at inference and test-time flip, both measured to be no gain (docs/detector.md)
RETIRED = {"refine_passes": 1, "flip_test": False}


@dataclass
class DetectorConfig:
    """Geometry of the BEV grid, network widths, target and decoding parameters.

    x and y ranges are in the sensor frame, z in the **ground frame** (sensor z + the frames' mount
    height), metres: the network always sees the ground near z = 0, so sources and targets with
    different mount heights (Waymo 2.0 m, KITTI 1.73 m) agree. (-1.27, 2.73) is KITTI's -3..1 m in
    its sensor frame. The BEV grid has rows along y and columns along x; the heads run at
    `out_stride` pillars per cell.
    """

    # input
    x_range_m: tuple[float, float] = (0.0, 70.4)
    y_range_m: tuple[float, float] = (-40.0, 40.0)
    z_range_m: tuple[float, float] = (-1.27, 2.73)  # ground frame
    pillar_m: float = 0.32
    features: str = "xyz"  # "xyz" or "xyzi"
    sensor: str = "kitti"  # profile of the (first) training frame set, for provenance
    mount_height_m: float = 1.73  # its mount height: predict()'s default ground for PTSN scaling
    # network
    pfn_channels: int = 32
    block_channels: tuple[int, int, int] = (32, 64, 128)  # strides 2, 4, 8 (in pillars)
    block_layers: tuple[int, int, int] = (2, 3, 3)  # 3x3 convs after each strided conv
    up_channels: int = 32  # per scale, after upsampling to out_stride
    head_channels: int = 64
    # targets and losses
    min_radius_cells: int = 2
    min_gaussian_overlap: float = 0.1
    max_objects: int = 128
    regression_radius_cells: int = 0  # box + IoU heads learn at the (2r+1)^2 cells around a centre
    iou_peak_cells: int = 32  # the IoU head also learns at this many heatmap peaks per frame
    loss_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)  # heatmap, box regression, IoU
    # per regression channel: offset x, y (cells), z (m), log l, w, h, sin 2yaw, cos 2yaw
    regression_weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
    # second stage (refine.py): a PointNet on each box's points predicts a residual box + its IoU
    refine: bool = True
    refine_points: int = 128  # points sampled per box
    refine_margin_m: float = 0.4  # the box grows by this on every side to gather them
    refine_channels: int = 128  # point MLP widths c/2, c, 2c; box MLP 2c
    refine_train_peaks: int = 64  # first-stage peaks per frame the refiner trains on (docs: 32)
    refine_weights: tuple[float, float] = (1.0, 1.0)  # residual, IoU
    # refined score = first-stage score^(1 - a) * refined IoU^a; with the refiner trained on 64
    # peaks, a = 0.5 beat 0.3 in AP and in boxes on no car at score 0.3 (docs/detector.md)
    refine_alpha: float = 0.5
    # decoding
    top_k: int = 100
    score_threshold: float = 0.05
    nms_iou: float = 0.1
    iou_alpha: float = 0.5  # score = heat^(1 - alpha) * iou^alpha (SECOND-IoU / CIA-SSD style)

    @property
    def out_stride(self) -> int:
        return 2

    @property
    def grid_size(self) -> tuple[int, int]:
        """(rows along y, columns along x) of the pillar grid, padded to a multiple of 8."""
        rows = math.ceil((self.y_range_m[1] - self.y_range_m[0]) / self.pillar_m - 1e-6)
        cols = math.ceil((self.x_range_m[1] - self.x_range_m[0]) / self.pillar_m - 1e-6)
        return math.ceil(rows / 8) * 8, math.ceil(cols / 8) * 8

    @property
    def head_size(self) -> tuple[int, int]:
        rows, cols = self.grid_size
        return rows // self.out_stride, cols // self.out_stride

    @property
    def cell_m(self) -> float:
        """Size of one head cell in metres."""
        return self.pillar_m * self.out_stride

    @property
    def point_dims(self) -> int:
        return 4 if self.features == "xyzi" else 3

    @property
    def name(self) -> str:
        """The detector's name for reports: the one-stage net, or with its second stage."""
        return "pillar-centerpoint-iou" + ("-refine" if self.refine else "")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> DetectorConfig:
        """The config of a model.json's `config` block (or of --detector-config overrides);
        unknown keys are a ValueError. RETIRED keys are read at their one value and dropped."""
        values = dict(values)
        for key, only in RETIRED.items():
            if key in values and (value := values.pop(key)) != only:
                raise ValueError(
                    f"detector config key {key} = {value!r} is no longer supported "
                    f"(only {only!r}: an option measured to be no gain)"
                )
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ValueError(f"unknown detector config keys: {', '.join(unknown)}")
        converted = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
        return cls(**converted)
