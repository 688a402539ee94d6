"""The detector's hyper-parameters in one dataclass, saved with every checkpoint (model.json)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from dali_cli.quantities import is_profile_name

# fields earlier models' model.json carry, with the one value still read: a second refinement
# pass at inference, test-time flip and a refiner without the flip logit, each measured to be no
# gain (docs/detector.md, docs/experiments.md)
RETIRED = {"refine_passes": 1, "flip_test": False, "refine_flip": True}


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
    # the scans the model is for (detector/scans_for.py): the sensor profile of the frames it was
    # trained on, or adapted to (retrain, self-train: the target's), its mount height (predict()'s
    # default ground, the pivot of PTSN scaling) and the front view (degrees of azimuth about +x)
    # those frames were cropped to, None for full scans (detect's default --front-deg)
    sensor: str = "kitti"
    mount_height_m: float = 1.73
    front_deg: float | None = None
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
    # which end of the heading axis is the front: a two-bin classifier in the heads and a flip
    # logit in the second stage (direction.py; OpenPCDet SECOND's dir_offset). Weight 1, not
    # SECOND's 0.2: within dali's short budgets 0.2 had not learnt it (toy cars with a cabin,
    # 360 steps: 10 of 23 true positives backwards at 0.2, 0 of 24 at 1; on synthetic Waymo-like
    # frames, three seeds: 4.1 % against 8.3 % backwards, for less AP_3D; docs/experiments.md)
    direction: bool = True
    direction_offset: float = math.pi / 4
    direction_weight: float = 1.0
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
        for name, value in converted.items():
            check_field(name, value, cls.__dataclass_fields__[name].default)
        config = cls(**converted)
        config.check_geometry()
        return config

    def check_geometry(self) -> None:
        """Ranges increasing, the grid and the widths within LIMITS (memory); ValueError."""
        for name in ("x_range_m", "y_range_m", "z_range_m"):
            low, high = getattr(self, name)
            if not low < high:
                raise ValueError(f"{name}: expected [low, high] with low < high, got {low}, {high}")
        rows, cols = self.grid_size
        if rows * cols > MAX_GRID_CELLS:
            raise ValueError(
                f"pillar_m {self.pillar_m:g} over x_range_m {list(self.x_range_m)} and y_range_m "
                f"{list(self.y_range_m)} makes a {rows} x {cols} pillar grid, more than "
                f"{MAX_GRID_CELLS} cells"
            )
        widths = {
            "pfn_channels": self.pfn_channels,
            "block_channels": max(self.block_channels),
            "up_channels": 3 * self.up_channels,
            "head_channels": self.head_channels,
        }
        widest = max(widths, key=widths.get)
        feature_bytes = rows * cols * widths[widest] * 4
        if feature_bytes > MAX_FEATURE_BYTES:
            raise ValueError(
                f"pillar_m and {widest}: a {rows} x {cols} pillar grid with {widths[widest]} "
                f"channels needs {feature_bytes / 2**30:.0f} GiB for one feature map, more than "
                f"{MAX_FEATURE_BYTES / 2**30:.0f} GiB: use a larger pillar_m or narrower layers"
            )


# bounds of every numeric field (inclusive; None: unbounded), checked by from_dict so a
# hand-edited model.json or --detector-config fails with the field's name, not inside torch
MAX_CHANNELS = 4096
MAX_GRID_CELLS = 4096 * 4096
MAX_FEATURE_BYTES = 16 * 2**30  # one float32 BEV feature map of one frame
BOUNDS: dict[str, tuple[float | None, float | None]] = {
    "pillar_m": (1e-3, 100.0),
    "mount_height_m": (0.0, 100.0),
    "front_deg": (1e-3, 360.0),
    "pfn_channels": (1, MAX_CHANNELS),
    "block_channels": (1, MAX_CHANNELS),
    "block_layers": (0, 64),
    "up_channels": (1, MAX_CHANNELS),
    "head_channels": (1, MAX_CHANNELS),
    "min_radius_cells": (0, 1000),
    "min_gaussian_overlap": (0.0, 1.0),
    "max_objects": (1, 100_000),
    "regression_radius_cells": (0, 100),
    "iou_peak_cells": (0, 100_000),
    "refine_points": (1, 100_000),
    "refine_margin_m": (0.0, 100.0),
    "refine_channels": (1, MAX_CHANNELS),
    "refine_train_peaks": (0, 100_000),
    "refine_passes": (0, 100),
    "refine_alpha": (0.0, 1.0),
    "top_k": (1, 100_000),
    "score_threshold": (0.0, 1.0),
    "nms_iou": (0.0, 1.0),
    "iou_alpha": (0.0, 1.0),
    "direction_offset": (-math.pi, math.pi),
    "direction_weight": (0.0, 1e6),
    "loss_weights": (0.0, 1e6),
    "regression_weights": (0.0, 1e6),
    "refine_weights": (0.0, 1e6),
    "x_range_m": (-1e4, 1e4),
    "y_range_m": (-1e4, 1e4),
    "z_range_m": (-1e4, 1e4),
}

# text fields: one of a few words, or the name of a sensors.toml profile (a word, never a path)
CHOICES: dict[str, tuple[str, ...]] = {"features": ("xyz", "xyzi")}
PROFILE_NAMES = ("sensor",)


def check_field(name: str, value, default) -> None:
    """`value` has the kind of `default` (bool, str, int, finite float, a tuple of as many of
    them) and lies within BOUNDS[name]; ValueError naming the field otherwise. A field whose
    default is None (front_deg) takes None or a number."""
    if default is None and value is None:
        return
    if isinstance(default, tuple):
        if not isinstance(value, tuple) or len(value) != len(default):
            shown = repr(value)[:80]
            raise ValueError(f"{name}: expected a list of {len(default)} numbers, got {shown}")
        for item in value:
            check_field(name, item, default[0])
        return
    if isinstance(default, bool) or isinstance(default, str):
        if type(value) is not type(default):
            raise ValueError(f"{name}: expected a {type(default).__name__}, got {value!r}")
        if name in CHOICES and value not in CHOICES[name]:
            raise ValueError(f"{name}: expected one of {', '.join(CHOICES[name])}, got {value!r}")
        if name in PROFILE_NAMES and not is_profile_name(value):
            raise ValueError(f"{name}: expected a sensor profile name, got {value!r}"[:200])
        return
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{name}: expected a number, got {value!r}"[:200])
    if isinstance(default, int) and not isinstance(value, int):
        raise ValueError(f"{name}: expected an integer, got {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")
    low, high = BOUNDS.get(name, (None, None))
    if (low is not None and value < low) or (high is not None and value > high):
        shown = f"{value:g}" if isinstance(value, float) or abs(value) < 10**15 else "a huge number"
        raise ValueError(f"{name}: {shown} is outside [{low:g}, {high:g}]")
