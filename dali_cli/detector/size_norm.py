"""A labelled frame set seen with a model's size convention (SN): every car box's l, w, h shifted
by a fixed delta (its bottom centre and yaw kept) and the points inside it moved with it.

This is the view `dali pretrain --size-norm sn` and `dali retrain --size-norm sn` train on
(dali_cli.detector.size_normalize, the same `augment.scale_objects`). A model trained that way
outputs cars of the shifted size, so its source-domain validation (the forgetting check) is only
fair on source frames shifted the same way; `dali size-norm` writes them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dali_cli.runtime.errors import StageError


def shift_frame(
    points: np.ndarray, boxes: np.ndarray, delta_lwh: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(points `(n, 4)` float32, boxes `(m, 7)`) with every box's l, w, h += delta_lwh `(3,)`
    (metres) about its bottom centre and the points within 5 cm of it scaled with it."""
    from dali_cli.detector.augment import scale_objects

    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    if len(boxes) == 0:
        return np.asarray(points, np.float32), boxes
    factors = (boxes[:, 3:6] + delta_lwh) / boxes[:, 3:6]  # (m, 3)
    moved, shifted = scale_objects(np.asarray(points, np.float32), boxes, factors)
    return moved.astype(np.float32, copy=False), shifted


def too_small(boxes: np.ndarray, delta_lwh: np.ndarray) -> np.ndarray:
    """Rows `(m,)` bool of boxes `(m, 7)` that the shift would leave without a positive size."""
    return (np.asarray(boxes, np.float64).reshape(-1, 7)[:, 3:6] + delta_lwh <= 0).any(axis=1)


def model_delta(model_dir: str | Path) -> tuple[float, float, float]:
    """The SN shift (l, w, h in m) a model's training applied to its source, from its card."""
    from dali_cli.store.model_card import read_card

    card = read_card(model_dir)
    if card.sn_delta_lwh_m is None:
        raise StageError(
            f"{model_dir}: the model was not trained with a size shift (size_norm "
            f"{card.size_norm!r}): its source needs no size-norm view; evaluate on the frames "
            "as they are"
        )
    return tuple(float(v) for v in card.sn_delta_lwh_m)
