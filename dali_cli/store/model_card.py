"""The model card: what training recorded about a detector that later stages rely on.

One typed record, written by pretrain (and carried forward by retrain and self-train) under the
`card` key of model.json, and read by every stage that needs it: the source sensor and mount
height, the source's mean car size, the size normalization (SN offset or ROS range) the model was
trained with. Checkpoints written before the card existed keep these facts in `provenance`,
`metrics` and `config`; `ModelCard.from_meta` reads both layouts, so no reader looks inside
model.json by itself (a second, diverging reader once made `--target-size ros` ignore a real
checkpoint's ROS range and source mean).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from dali_cli import quantities
from dali_cli.store.artifacts import ArtifactError, read_json
from dali_cli.store.json_numbers import finite_number, finite_numbers

META_NAME = "model.json"
SIZE_NORMS = ("none", "sn", "ros")


def _of_kind(kind: quantities.Quantity, value, count: int) -> tuple[float, ...] | None:
    """`count` numbers of `kind` (quantities) from a JSON list, else None."""
    numbers = finite_numbers(value, count)
    if numbers is None or any(kind.problem(n) is not None for n in numbers):
        return None
    return numbers


def _size(value) -> tuple[float, float, float] | None:
    """(l, w, h) of a car in metres, else None."""
    return _of_kind(quantities.CAR_SIZE_M, value, 3)


def _delta(value) -> tuple[float, float, float] | None:
    """An SN size offset (l, w, h) in metres (each may be negative), else None."""
    return _of_kind(quantities.SIZE_DELTA_M, value, 3)


def _pair(value) -> tuple[float, float] | None:
    """(lo, hi) ROS scale factors, lo <= hi, else None."""
    pair = _of_kind(quantities.SCALE, value, 2)
    return pair if pair is not None and pair[0] <= pair[1] else None


def _text(value) -> str | None:
    return value if isinstance(value, str) and value else None


def _profile(value) -> str | None:
    """A sensor profile name (never a path), else None."""
    return value if isinstance(value, str) and quantities.is_profile_name(value) else None


@dataclass(frozen=True)
class ModelCard:
    """What a detector was trained on and how (sizes in metres)."""

    detector: str | None = None  # network name, e.g. pillar-centerpoint-iou-refine
    stage: str | None = None  # pretrain | retrain | self-train: the stage that wrote it
    source_sensor: str | None = None  # sensor profile of the labelled source frames
    source_mount_height_m: float | None = None  # the source sensor's height above the ground
    source_mean_lwh_m: tuple[float, float, float] | None = None  # mean labelled source car
    size_norm: str = "none"  # none | sn | ros
    sn_delta_lwh_m: tuple[float, float, float] | None = None  # SN: size offset added to labels
    ros_range: tuple[float, float] | None = None  # ROS: object scale factors trained with
    target_profile: str | None = None  # SN: the target profile whose mean size was used

    @property
    def ros_factor(self) -> float | None:
        """The mean ROS factor (middle of the range), None when trained without ROS."""
        return None if self.ros_range is None else 0.5 * (self.ros_range[0] + self.ros_range[1])

    def to_dict(self) -> dict:
        document = dataclasses.asdict(self)
        for key, value in document.items():
            if isinstance(value, tuple):
                document[key] = list(value)
        return document

    def carried_forward(self, stage: str) -> ModelCard:
        """The card of a model trained from this one (retrain, self-train): same source facts."""
        return dataclasses.replace(self, stage=stage)

    @classmethod
    def from_meta(cls, meta: dict) -> ModelCard:
        """The card in a model.json document: its `card` block, else what older checkpoints
        recorded in `provenance`, `metrics` and `config`."""
        if not isinstance(meta, dict):
            raise ValueError("model.json is not a JSON object")
        card = meta.get("card")
        if isinstance(card, dict):
            return cls._from_card(card)
        provenance = meta.get("provenance") if isinstance(meta.get("provenance"), dict) else {}
        metrics = meta.get("metrics") if isinstance(meta.get("metrics"), dict) else {}
        config = meta.get("config") if isinstance(meta.get("config"), dict) else {}
        return cls._from_card(
            {
                "detector": _text(meta.get("detector")) or _text(config.get("name")),
                "stage": provenance.get("stage"),
                "source_sensor": _text(provenance.get("source_sensor")) or config.get("sensor"),
                "source_mount_height_m": config.get("mount_height_m"),
                "source_mean_lwh_m": metrics.get("source_mean_lwh_m"),
                "size_norm": provenance.get("size_norm"),
                "sn_delta_lwh_m": provenance.get("sn_delta_lwh"),
                "ros_range": provenance.get("ros_range"),
                "target_profile": provenance.get("target_profile"),
            }
        )

    @classmethod
    def _from_card(cls, card: dict) -> ModelCard:
        """A card from a JSON block, every field type-checked (a bad value reads as unknown)."""
        # cards written before model.json's config named the adapted-to sensor called it
        # mount_height_m: one name now has one meaning, the height of the sensor a model is for
        mount = card.get("source_mount_height_m", card.get("mount_height_m"))
        size_norm = card.get("size_norm")
        return cls(
            detector=_text(card.get("detector")),
            stage=_text(card.get("stage")),
            source_sensor=_profile(card.get("source_sensor")),
            source_mount_height_m=mount
            if (mount := finite_number(mount)) is not None
            and quantities.MOUNT_HEIGHT_M.problem(mount) is None
            else None,
            source_mean_lwh_m=_size(card.get("source_mean_lwh_m")),
            size_norm=size_norm if size_norm in SIZE_NORMS else "none",
            sn_delta_lwh_m=_delta(card.get("sn_delta_lwh_m")),
            ros_range=_pair(card.get("ros_range")),
            target_profile=_profile(card.get("target_profile")),
        )


def read_meta(model_dir: str | Path) -> dict:
    """model.json of a model directory as a dict; ArtifactError when missing or not JSON."""
    path = Path(model_dir) / META_NAME
    document = read_json(
        path, f"not found (is {model_dir} a model directory?)", "not a dali model description"
    )
    if not isinstance(document, dict):
        raise ArtifactError(f"{path}: not a dali model description (not a JSON object)")
    return document


def has_direction(model_dir: str | Path) -> bool:
    """Whether the model of `model_dir` predicts full headings (a direction classifier): false
    for a model.json from before it, whose config has no "direction"."""
    config = read_meta(model_dir).get("config")
    return bool(config.get("direction", False)) if isinstance(config, dict) else False


def read_card(model_dir: str | Path) -> ModelCard:
    """The model card of a model directory (see ModelCard.from_meta)."""
    return ModelCard.from_meta(read_meta(model_dir))
