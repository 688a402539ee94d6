"""Training data: labelled frame sets (ground frame), their points held in memory or read from
frames.zarr when a sample needs them (`FramePoints`), and the augmentation pipeline that turns
a frame into one training sample."""

from __future__ import annotations

import bisect
import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from dali_cli.detector import augment
from dali_cli.detector.config import DetectorConfig
from dali_cli.store.artifacts import ArtifactError, ChunkCache, FrameSet, read_boxes

CACHED_CHUNKS = 2  # point chunks (up to 32 MiB each) a streaming reader keeps decoded


class PreparedFrames(ChunkCache):
    """The prepared frames (clipped and transformed, read-only arrays) a process used last, up to
    `max_bytes` in all, least recently used first out, keyed by (reader, frame index). A training
    set that fits is decoded and prepared once per process, as when it was held in memory; a
    larger one costs at most `max_bytes` (runtime.limits "frame_cache_bytes",
    DALI_FRAME_CACHE_BYTES), whatever the number of sets and frames."""

    def __init__(self, max_bytes: int):
        super().__init__(max_chunks=None, max_bytes=max_bytes)

    def put(self, key: tuple, points: np.ndarray) -> np.ndarray:
        points.flags.writeable = False  # shared by every sample made of it
        return super().put(key, points)


_PREPARED: PreparedFrames | None = None


def new_token() -> str:
    """A key no other reader of this run has: a reader's frames in the PreparedFrames."""
    import uuid

    return uuid.uuid4().hex


def prepared_frames() -> PreparedFrames:
    """This process's PreparedFrames (made at first use, with the limit of the environment)."""
    global _PREPARED
    if _PREPARED is None:
        from dali_cli.runtime.limits import limit

        _PREPARED = PreparedFrames(limit("frame_cache_bytes"))
    return _PREPARED


@dataclass
class Augmentation:
    """Which augmentations run, with their ranges. `object_scale` is ROS (None = off)."""

    gt_sampling: bool = True
    gt_sample_count: int = 45  # paste cars until a frame has about this many (see docs: Ablations)
    flip: bool = True
    rotation_rad: float = np.pi / 8  # global rotation U(-r, r); pi/4: -1.6 / -8.0 AP_3D (2 seeds)
    scaling: tuple[float, float] = (0.95, 1.05)  # global scaling about the ground
    object_noise: bool = True
    object_scale: tuple[float, float] | None = None  # ROS: U(lo, hi) per object, l, w, h alike

    @classmethod
    def none(cls) -> Augmentation:
        return cls(False, 0, False, 0.0, (1.0, 1.0), False, None)


def clip_points(points: np.ndarray, mount_m: float, far_m: float, reach_rad: float) -> np.ndarray:
    """The points `(n, 4)` float32 (sensor frame) global rotation can bring into the detection
    range (closer than `far_m`, less than `reach_rad` off +x), moved to the ground frame
    (z + `mount_m`); a new array."""
    keep = (np.hypot(points[:, 0], points[:, 1]) < far_m) & (
        np.abs(np.arctan2(points[:, 1], points[:, 0])) < reach_rad
    )
    points = points[keep].copy()
    points[:, 2] += mount_m
    return points


class FramePoints(Sequence):
    """The points of a FrameSet's frames as training sees them, read from frames.zarr when asked
    for: item i is frame i clipped (`clip_points`) and then changed by `transforms`, in order:
    ("sn", delta_lwh (3,), boxes) shifts the size of frame i's boxes[i] (m_i, 7) with their points
    (size_norm.shift_frame); ("scale", s) scales about the ground (scale_ground_points). Each
    process keeps the last CACHED_CHUNKS decoded chunks it read and the prepared frames it used
    last (PreparedFrames: bounded memory); iterating reads the frames in order, block-wise. Picklable: a DataLoader worker opens the set itself."""

    def __init__(
        self, directory: str | Path, mount_m: float, far_m: float, reach_rad: float,
        transforms: tuple = (),
    ):  # fmt: skip
        self.directory = Path(directory)
        self.clip = (float(mount_m), float(far_m), float(reach_rad))
        self.transforms = tuple(transforms)
        self._frames: FrameSet | None = None
        self._cache = ChunkCache(CACHED_CHUNKS)
        self._length = len(self.frameset())
        self._token = new_token()

    def frameset(self) -> FrameSet:
        if self._frames is None:
            self._frames = FrameSet(self.directory)
        return self._frames

    def __len__(self) -> int:
        return self._length

    def __getitem__(self, index: int) -> np.ndarray:
        if not -self._length <= index < self._length:
            raise IndexError(index)
        index = index % self._length
        kept, key = prepared_frames(), (self._token, index)
        points = kept.get(key)
        if points is None:
            points = kept.put(key, self._prepared(index, self.frameset().frame(index, self._cache)))
        return points

    def __iter__(self):
        for index, (_, points) in enumerate(self.frameset().iter_frames()):
            yield self._prepared(index, points)

    def _prepared(self, index: int, points: np.ndarray) -> np.ndarray:
        from dali_cli.detector.size_norm import shift_frame
        from dali_cli.geometry import scale_ground_points

        points = clip_points(points, *self.clip)
        for kind, value, *rest in self.transforms:
            if kind == "sn":
                points = shift_frame(points, rest[0][index], value)[0]
            else:
                points = scale_ground_points(points, value)
        return points

    def then(self, *transform) -> FramePoints:
        """These points with one more transform (see the class)."""
        out = FramePoints.__new__(FramePoints)
        state = {**self.__getstate__(), "transforms": (*self.transforms, transform)}
        out.__setstate__({**state, "_token": new_token()})  # other points: other cache keys
        return out

    def identity(self) -> dict:
        """What the points are made of: the frame set's content hash, the clipping and the
        transforms (an SN transform's boxes by their hash): the key of caches derived from them."""
        from dali_cli.store.manifest import content_hash

        steps = []
        for kind, value, *rest in self.transforms:
            step = {"kind": kind, "value": np.asarray(value, np.float64).tolist()}
            if rest:
                step["boxes"] = boxes_hash(rest[0])
            steps.append(step)
        return {"frames": content_hash(self.directory), "clip": list(self.clip), "steps": steps}

    def __getstate__(self) -> dict:
        return {
            "directory": self.directory, "clip": self.clip, "transforms": self.transforms,
            "_length": self._length, "_token": self._token,
        }  # fmt: skip

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._frames, self._cache = None, ChunkCache(CACHED_CHUNKS)


class ChainedPoints(Sequence):
    """Several frame sequences (lists or FramePoints) as one: frame i of the chain is frame
    i - start of the part it falls in."""

    def __init__(self, parts: list):
        self.parts = list(parts)
        self.starts = np.concatenate([[0], np.cumsum([len(p) for p in self.parts])]).tolist()

    def __len__(self) -> int:
        return self.starts[-1]

    def __getitem__(self, index: int) -> np.ndarray:
        if not -len(self) <= index < len(self):
            raise IndexError(index)
        index = index % len(self)
        part = bisect.bisect_right(self.starts, index) - 1
        return self.parts[part][index - self.starts[part]]

    def __iter__(self):
        for part in self.parts:
            yield from part

    def identity(self) -> dict:
        return {"parts": [points_identity(p) for p in self.parts]}


def chain_points(parts: list) -> list | ChainedPoints:
    """The frames of `parts` one after another: a list when every part is one (in memory),
    else a ChainedPoints that reads them when asked."""
    if all(isinstance(p, list) for p in parts):
        return [points for part in parts for points in part]
    return ChainedPoints(parts)


def points_identity(points) -> dict:
    """FramePoints/ChainedPoints.identity, or the hash of points held in memory."""
    if hasattr(points, "identity"):
        return points.identity()
    return {"arrays": boxes_hash(points)}


def boxes_hash(arrays) -> str:
    """A hash of a list of arrays (their shapes, dtypes and bytes)."""
    import hashlib

    digest = hashlib.blake2b(digest_size=16)
    for array in arrays:
        array = np.ascontiguousarray(array)
        digest.update(f"{array.dtype}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


@dataclass
class LabeledFrames:
    """A labelled training set. points[i]: (n_i, 4) float32 and boxes[i]: (m_i, 7) float64, both in
    the ground frame (sensor z + mount_height_m); `points` a list in memory or a FramePoints /
    ChainedPoints that reads frame i from frames.zarr when asked."""

    name: str
    sensor: str
    mount_height_m: float
    frame_ids: list[str]
    points: Sequence[np.ndarray]
    boxes: list[np.ndarray]
    database: augment.ObjectDatabase | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def num_boxes(self) -> int:
        return int(sum(len(b) for b in self.boxes))

    def mean_lwh(self) -> np.ndarray:
        """Mean l, w, h (3,) of all boxes."""
        boxes = np.concatenate(self.boxes) if self.boxes else np.zeros((0, 7))
        return boxes[:, 3:6].mean(axis=0) if len(boxes) else np.full(3, np.nan)


def load_labeled(
    data_dir: str | Path,
    config: DetectorConfig,
    boxes_dir: str | Path | None = None,
    labels: tuple[str, ...] = ("Car",),
    min_points: int = 1,
    sensors_path: str | Path | None = None,
    stream: bool = False,
) -> LabeledFrames:
    """Read a FrameSet and its boxes.parquet (same directory unless `boxes_dir`) into memory.
    With `stream` only the boxes stay in memory: every frame is read once to choose them, and
    `points` is a FramePoints that reads a frame again when asked (memory independent of the
    number of frames).

    Points and boxes that global rotation (<= 45 deg) cannot bring into the detection range are
    dropped (beyond its far corner + 10 m, or more than 135 deg off +x for a front range); boxes
    of other labels or with fewer than `min_points` points are not targets. A box of `labels`
    outside dali_cli.labels.plausibility's limits (size, distance from the sensor) is an ArtifactError
    naming the file, row, frame and field: corrupt labels or labels not in metres.
    """
    from dali_cli.geometry import count_points_in_boxes
    from dali_cli.labels import plausibility
    from dali_cli.sensors import get_profile

    frames = FrameSet(data_dir)
    table = read_boxes(boxes_dir or data_dir)
    if not frames.sensor:
        raise ArtifactError(f"{frames.path}: attrs has no 'sensor' (needed for the mount height)")
    profile = get_profile(frames.sensor, sensors_path)
    mount = profile.mount_height_m
    known = set(frames.frame_ids)
    unknown = sorted(set(table.frame_id.astype(str)) - known)
    if unknown:
        raise ArtifactError(
            f"{Path(boxes_dir or data_dir) / 'boxes.parquet'}: frame_id '{unknown[0]}' is not in {frames.path}"
        )
    targets = np.isin(table["label"].astype(str), labels)
    plausibility.refuse_implausible(
        table.boxes,
        targets,
        str(Path(boxes_dir or data_dir) / "boxes.parquet"),
        table.frame_id,
        profile.max_range_m,
    )
    table = table.select(targets)
    rows = table.rows_by_frame()
    far = (
        np.hypot(max(abs(v) for v in config.x_range_m), max(abs(v) for v in config.y_range_m)) + 10
    )
    reach = np.radians(135.0) if config.x_range_m[0] >= 0 else np.pi + 1e-9
    all_points, all_boxes = [], []
    for frame_id, points in frames.iter_frames():
        # only what global rotation (<= 45 deg) can bring into the range: radius and azimuth
        points = clip_points(points, mount, far, reach)
        boxes = table.select(rows.get(frame_id, np.zeros(0, np.int64))).boxes
        boxes[:, 2] += mount
        if len(boxes):
            visible = np.abs(np.arctan2(boxes[:, 1], boxes[:, 0])) < reach
            boxes = boxes[visible & (count_points_in_boxes(points, boxes) >= min_points)]
        if not stream:
            all_points.append(points)
        all_boxes.append(boxes)
    if stream:
        all_points = FramePoints(data_dir, mount, far, reach)
    return LabeledFrames(
        str(data_dir), frames.sensor, mount, list(frames.frame_ids), all_points, all_boxes
    )


def size_normalize(frames: LabeledFrames, delta_lwh: np.ndarray) -> LabeledFrames:
    """SN (Wang et al. 2020): every box's l, w, h += delta_lwh, its points scaled with it."""
    from dali_cli.detector.size_norm import shift_frame

    delta_lwh = np.asarray(delta_lwh, np.float64).reshape(3)
    if not isinstance(frames.points, list):  # read when asked: the boxes now, the points then
        nothing = np.zeros((0, 4), np.float32)  # a box's new size does not depend on points
        boxes = [shift_frame(nothing, b, delta_lwh)[1] for b in frames.boxes]
        points = frames.points.then("sn", delta_lwh, list(frames.boxes))
        return dataclasses.replace(frames, points=points, boxes=boxes, database=None)
    points, boxes = [], []
    for frame_points, frame_boxes in zip(frames.points, frames.boxes, strict=True):
        new_points, new_boxes = shift_frame(frame_points, frame_boxes, delta_lwh)
        points.append(new_points)
        boxes.append(new_boxes)
    return LabeledFrames(
        frames.name, frames.sensor, frames.mount_height_m, frames.frame_ids, points, boxes
    )


def scale_about_ground(frames: LabeledFrames, scale: float) -> LabeledFrames:
    """PTSN's view of a labelled set: points (x, y, z) and boxes (centres and l, w, h) multiplied
    by `scale` in the ground frame (the ground plane stays put; intensity and yaw unchanged).
    This is the cloud `Detector.predict(..., scale=scale)` feeds the network."""
    from dali_cli.geometry import scale_ground_boxes, scale_ground_points

    if isinstance(frames.points, list):
        points = [scale_ground_points(p, scale) for p in frames.points]  # (n, 4): intensity kept
    else:  # read when asked
        points = frames.points.then("scale", float(scale))
    boxes = [scale_ground_boxes(b, scale) for b in frames.boxes]  # (m, 7): yaw kept
    return LabeledFrames(
        frames.name, frames.sensor, frames.mount_height_m, frames.frame_ids, points, boxes
    )


def detection_region(config: DetectorConfig) -> tuple[float, float, float, float]:
    return (*config.x_range_m, *config.y_range_m)


class Sample(NamedTuple):
    """One augmented training frame, ground frame: points (n, 4) float32, boxes (m, 7) float64
    (the targets)."""

    points: np.ndarray
    boxes: np.ndarray


def augmented_sample(
    frames: LabeledFrames, index: int, rng: np.random.Generator, settings: Augmentation
) -> Sample:
    """One augmented frame: ground-truth sampling, object scaling and noise, then the frame's
    flip, rotation and scaling, each drawn from `rng` in that order."""
    points, boxes = frames.points[index], frames.boxes[index]
    if settings.gt_sampling and frames.database is not None:
        points, boxes = augment.sample_ground_truth(
            points, boxes, frames.database, rng, settings.gt_sample_count
        )
    if settings.object_scale is not None and len(boxes):
        factor = rng.uniform(*settings.object_scale, size=len(boxes))
        points, boxes = augment.scale_objects(points, boxes, np.repeat(factor[:, None], 3, axis=1))
    if settings.object_noise:
        points, boxes = augment.object_noise(points, boxes, rng)
    if settings.flip and rng.random() < 0.5:
        points, boxes = augment.flip_y(points, boxes)
    if settings.rotation_rad > 0:
        points, boxes = augment.rotate_scene(
            points, boxes, rng.uniform(-settings.rotation_rad, settings.rotation_rad)
        )
    if settings.scaling != (1.0, 1.0):
        points, boxes = augment.scale_scene(points, boxes, rng.uniform(*settings.scaling))
    return Sample(points, boxes)
