"""Plausibility limits of boxes: the sizes a road object can have and how far from the LiDAR its
centre can lie. The one place these limits live; pseudo-label, ppcg-rc/cf and the training-label
reader (pretrain, retrain) apply them (docs/ppcg.md, "Implausible boxes").

The limits are deliberately loose: they catch corrupt values (a pseudo box 1,000 km long, a label
in millimetres, l = 1e30), never a real object. Boxes are `(N, 7)` float64 x, y, z, l, w, h, yaw
in the sensor frame (metres, radians).
"""

from __future__ import annotations

import numpy as np

MIN_SIZE_M = 0.01  # thinner than 1 cm in any dimension is no object
# l and w: the longest road vehicles (road trains, about 53 m); w gets the same limit because
# a labeller may swap l and w with the yaw turned by 90 degrees
MAX_HORIZONTAL_SIZE_M = 60.0
MAX_HEIGHT_M = 10.0  # double-deck buses are 4.4 m, the tallest legal loads about 5 m
# a box centre may lie beyond the sensor's max range (part of the object inside), not twice as far
RANGE_FACTOR = 2.0
DEFAULT_MAX_RANGE_M = 250.0  # when no sensor profile is known: a long-range automotive LiDAR

FIELDS = ("x", "y", "z", "l", "w", "h", "yaw")
_MAX_SIZE_M = np.array([MAX_HORIZONTAL_SIZE_M, MAX_HORIZONTAL_SIZE_M, MAX_HEIGHT_M])  # (3,)


def max_center_distance_m(max_range_m: float | None = None) -> float:
    """Largest plausible distance (m) of a box centre from the sensor: RANGE_FACTOR x the sensor
    profile's max range (DEFAULT_MAX_RANGE_M when None)."""
    return RANGE_FACTOR * (DEFAULT_MAX_RANGE_M if max_range_m is None else float(max_range_m))


def plausible(boxes: np.ndarray, max_range_m: float | None = None) -> np.ndarray:
    """`(N,)` bool: finite, every size in [MIN_SIZE_M, limit] and the centre (3D distance from
    the sensor) within max_center_distance_m(max_range_m). boxes: `(N, 7)`."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    with np.errstate(invalid="ignore", over="ignore"):
        finite = np.isfinite(boxes).all(axis=1)
        sizes = boxes[:, 3:6]
        sized = ((sizes >= MIN_SIZE_M) & (sizes <= _MAX_SIZE_M)).all(axis=1)
        near = np.linalg.norm(boxes[:, :3], axis=1) <= max_center_distance_m(max_range_m)
    return finite & sized & near


def problem(box: np.ndarray, max_range_m: float | None = None) -> str | None:
    """Why one box `(7,)` is implausible (field, value and limit, in words), or None."""
    box = np.asarray(box, np.float64).reshape(7)
    for index in np.flatnonzero(~np.isfinite(box)):
        return f"field '{FIELDS[index]}' is {box[index]}"
    for index, limit in zip(range(3, 6), _MAX_SIZE_M, strict=True):
        if not MIN_SIZE_M <= box[index] <= limit:
            return (
                f"field '{FIELDS[index]}' = {box[index]:.6g} m is not a plausible object size "
                f"({MIN_SIZE_M:g} to {limit:g} m)"
            )
    distance = float(np.linalg.norm(box[:3]))
    limit = max_center_distance_m(max_range_m)
    if distance > limit:
        return (
            f"centre (x, y, z) is {distance:.6g} m from the sensor, beyond {limit:g} m "
            f"({RANGE_FACTOR:g} x the sensor's max range)"
        )
    return None


def refuse_implausible(
    boxes: np.ndarray,
    checked: np.ndarray,
    where: str,
    frame_ids,
    max_range_m: float | None = None,
) -> None:
    """The one rule for boxes read from a file (training labels, PPCG input, eval predictions and
    ground truth, imported labels): any `checked` row `(N,)` bool of `boxes` `(N, 7)` outside
    these limits is an ArtifactError naming `where` (the file), the row, its frame and the field,
    exit 1 and nothing written: corrupt values or values not in metres, never a real object."""
    from dali_cli.store.artifacts import ArtifactError

    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    bad = np.flatnonzero(np.asarray(checked, bool) & ~plausible(boxes, max_range_m))
    if len(bad):
        row = int(bad[0])
        raise ArtifactError(
            f"{where}: row {row} (frame '{frame_ids[row]}'): "
            f"{problem(boxes[row], max_range_m)} ({len(bad)} such rows; are the boxes in "
            "metres, in the sensor frame?)"
        )


def refuse_implausible_table(table, where: str, max_range_m: float | None = None) -> None:
    """`refuse_implausible` on a BoxTable's rows of positive size (the rows with a size of 0,
    such as KITTI's DontCare regions, are placeholders, not boxes)."""
    positive = (table.boxes[:, 3:6] > 0).all(axis=1)
    refuse_implausible(table.boxes, positive, where, table.frame_id, max_range_m)
