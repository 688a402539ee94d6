"""Test helper (not part of the package): an exact reference for which sensor rays hit a box,
and the rays CF's angular windows select for each box, to check that the windows lose no hit."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from dali_cli.ppcg.fitting import rays_to_model
from dali_cli.ppcg.window import box_windows, window_rays
from dali_cli.sensors import SensorProfile


def slab_hits(directions: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Reference: which unit rays `(R, 3)` from the origin intersect the solid box `(7,)`; `(R,)`
    bool."""
    origins, local_dirs = rays_to_model(np.zeros(3), directions, box)  # unit box [-0.5, 0.5]^3
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-0.5 - origins) / local_dirs
        t2 = (0.5 - origins) / local_dirs
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    return (t_far >= np.maximum(t_near, 0.0)) & (t_far > 0)


def hits_and_window_rays(
    profile: SensorProfile, boxes: np.ndarray
) -> Iterator[tuple[int, np.ndarray, np.ndarray, object]]:
    """For each box of `boxes` `(N, 7)`: (index, box, the indices of the profile's rays that hit
    it by `slab_hits`, the `window_rays` of its angular window)."""
    directions = profile.ray_pattern().directions.astype(np.float64)
    windows = box_windows(boxes)
    for index, box in enumerate(boxes):
        hits = np.flatnonzero(slab_hits(directions, box))
        rays = window_rays(
            profile,
            windows.azimuth_lo[index],
            windows.azimuth_hi[index],
            windows.elevation_lo[index],
            windows.elevation_hi[index],
        )
        yield index, box, hits, rays
