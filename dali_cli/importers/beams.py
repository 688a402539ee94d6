"""Beam removal: a 64-beam KITTI scan thinned to 32 or 16 beams, the field's stand-in for a
sparser real LiDAR (Wei et al., "LiDAR Distillation", ECCV 2022, pcdet/utils/downsample_utils.py).

Per scan, the elevation angle of every point, theta = atan2(z, sqrt(x^2 + y^2)), is clustered
into 64 beams by 1-D k-means; beams are numbered by their centres in ascending order (beam 0 is
the lowest, pointing furthest down), and beams 0, 2, 4, ... are kept for 32 beams, 0, 4, 8, ...
for 16. The protocol's `*` variants (`azimuth_half`) also keep every 2nd point of each kept beam
in azimuth order (azimuth counter-clockwise from +x in [0, 2 pi), the first point kept).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from dali_cli.runtime.errors import ParameterError

SCAN_BEAMS = 64  # KITTI's Velodyne HDL-64E
BEAM_CHOICES = (64, 32, 16)  # what a scan can be thinned to: every 1st, 2nd or 4th beam
MAX_ITERATIONS = 500  # Lloyd's iterations cost O(clusters log n); real scans converge in < 100


def elevations_rad(points: np.ndarray) -> np.ndarray:
    """Elevation angle of each point, `points (n, >=3)` -> `(n,)` float64 radians."""
    xyz = points[:, :3].astype(np.float64)  # (n, 3)
    return np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))


def azimuths_rad(points: np.ndarray) -> np.ndarray:
    """Azimuth of each point counter-clockwise from +x, `(n, >=2)` -> `(n,)` float64 in [0, 2 pi)."""
    azimuth = np.arctan2(points[:, 1].astype(np.float64), points[:, 0].astype(np.float64))
    return np.where(azimuth < 0.0, azimuth + 2.0 * np.pi, azimuth) % (2.0 * np.pi)


def cluster_1d(values: np.ndarray, clusters: int) -> tuple[np.ndarray, np.ndarray]:
    """1-D k-means of `values (n,)`: (labels `(n,)` int64 in [0, clusters), centres
    `(clusters,)` float64 ascending, so that label k is the k-th lowest cluster).

    Deterministic. In one dimension a cluster is a run of the sorted values, so both steps work
    on prefix sums of the sorted values: the centres start from bisection (split the run whose
    best cut lowers the squared error most, `clusters - 1` times: each cut falls where the
    values thin out, so a beam is never shared while a gap is left unsplit), then Lloyd's
    iterations (a cluster is the values between the midpoints of neighbouring centres) until
    no boundary moves. With fewer distinct values than clusters some clusters stay empty.
    """
    values = np.asarray(values, dtype=np.float64)
    n = len(values)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(clusters)
    order = np.argsort(values, kind="stable")  # (n,)
    ordered = values[order] - values.mean()  # (n,) ascending, centred for the squared sums
    sums = np.concatenate([[0.0], np.cumsum(ordered)])  # (n + 1,)
    squares = np.concatenate([[0.0], np.cumsum(ordered * ordered)])  # (n + 1,)
    bounds = _bisect(sums, squares, clusters)  # (clusters + 1,)
    for _ in range(MAX_ITERATIONS):
        counts = np.diff(bounds)  # (clusters,)
        means = (sums[bounds[1:]] - sums[bounds[:-1]]) / np.maximum(counts, 1)  # (clusters,)
        # an empty cluster sits at its boundary's value, between its neighbours' means
        centres = np.where(counts > 0, means, ordered[np.minimum(bounds[:-1], n - 1)])
        centres = np.maximum.accumulate(centres)  # sorted despite the sums' rounding
        midpoints = 0.5 * (centres[:-1] + centres[1:])  # (clusters - 1,)
        edges = np.searchsorted(ordered, midpoints)  # (clusters - 1,) first index above each
        if np.array_equal(edges, bounds[1:-1]):
            break
        bounds = np.concatenate([[0], edges, [n]])
    labels = np.empty(n, np.int64)
    labels[order] = np.repeat(np.arange(clusters), np.diff(bounds))
    return labels, centres + values.mean()


def _squared_error(sums: np.ndarray, squares: np.ndarray, start, stop):
    """Sum of squared deviations from their mean of the sorted values [start, stop) (arrays or
    ints), from their prefix `sums` and `squares` `(n + 1,)`."""
    count = np.maximum(stop - start, 1)
    total = sums[stop] - sums[start]
    return squares[stop] - squares[start] - total * total / count


def _bisect(sums: np.ndarray, squares: np.ndarray, clusters: int) -> np.ndarray:
    """Run boundaries `(clusters + 1,)` int64 of the sorted values (prefix `sums`, `squares`):
    the greedy bisection of `cluster_1d`."""

    def best_cut(start: int, stop: int) -> tuple[float, int, int, int]:
        if stop - start < 2:
            return (0.0, start, stop, start)
        cuts = np.arange(start + 1, stop)  # (stop - start - 1,)
        gain = _squared_error(sums, squares, start, stop) - (
            _squared_error(sums, squares, start, cuts) + _squared_error(sums, squares, cuts, stop)
        )
        best = int(np.argmax(gain))
        return (-float(gain[best]), start, stop, int(cuts[best]))

    n = len(sums) - 1
    runs = [best_cut(0, n)]  # a heap: the run whose cut gains most first
    for _ in range(clusters - 1):
        _, start, stop, cut = heapq.heappop(runs)
        heapq.heappush(runs, best_cut(start, cut))
        heapq.heappush(runs, best_cut(cut, stop))
    return np.array([0] + sorted(run[2] for run in runs), np.int64)


def beam_labels(points: np.ndarray, scan_beams: int = SCAN_BEAMS) -> np.ndarray:
    """Beam index of each point of one scan, `points (n, >=3)` -> `(n,)` int64 in
    [0, scan_beams): k-means of the points' elevations, 0 = the lowest beam."""
    return cluster_1d(elevations_rad(points), scan_beams)[0]


def keep_mask(
    points: np.ndarray, beams: int, azimuth_half: bool = False, scan_beams: int = SCAN_BEAMS
) -> np.ndarray:
    """`(n,)` bool: the points of one scan `points (n, >=3)` that a `beams`-beam sensor keeps
    (every `scan_beams // beams`-th beam from the lowest; with `azimuth_half` every 2nd point
    of each kept beam in azimuth order)."""
    if beams not in BEAM_CHOICES or scan_beams % beams:
        raise ValueError(f"beams must be one of {BEAM_CHOICES}, got {beams}")
    if beams == scan_beams and not azimuth_half:
        return np.ones(len(points), bool)
    labels = beam_labels(points, scan_beams)  # (n,)
    keep = labels % (scan_beams // beams) == 0  # (n,)
    if azimuth_half:
        kept = np.flatnonzero(keep)  # (m,)
        # sort the kept points by beam, then azimuth; the rank within its beam decides
        order = kept[np.lexsort((azimuths_rad(points[kept]), labels[kept]))]  # (m,)
        beam_of = labels[order]  # (m,) non-decreasing
        first = np.searchsorted(beam_of, beam_of)  # (m,) index of each beam's first point
        rank = np.arange(len(order)) - first  # (m,) position along the beam's azimuth
        keep[order[rank % 2 == 1]] = False
    return keep


def thin_beams(
    points: np.ndarray, beams: int, azimuth_half: bool = False, scan_beams: int = SCAN_BEAMS
) -> np.ndarray:
    """The points `(m, C)` of `points (n, C)` that `keep_mask` keeps (all of them at 64 beams
    without `azimuth_half`)."""
    if beams == scan_beams and not azimuth_half:
        return points
    return points[keep_mask(points, beams, azimuth_half, scan_beams)]


@dataclass(frozen=True)
class BeamThinning:
    """What an import keeps of each KITTI scan: `beams` of its 64 (64: all) and, with
    `azimuth_half`, every 2nd point of each kept beam. Applied to the whole scan, before any
    camera crop, so that the k-means sees every beam across the full revolution."""

    beams: int = SCAN_BEAMS
    azimuth_half: bool = False

    @classmethod
    def of(cls, beams: int, azimuth_half: bool) -> BeamThinning:
        """Checked: ParameterError naming the option for a count other than 64, 32 or 16, or
        azimuth halving at 64 beams (the protocol defines it for 32 and 16)."""
        if beams not in BEAM_CHOICES:
            raise ParameterError("beams", f"must be one of {BEAM_CHOICES}, got {beams}")
        if azimuth_half and beams == SCAN_BEAMS:
            raise ParameterError(
                ("beams", "beams_azimuth_half"),
                "azimuth halving needs --beams 32 or 16 (the protocol's 32* and 16*)",
            )
        return cls(int(beams), bool(azimuth_half))

    @property
    def active(self) -> bool:
        return self.beams != SCAN_BEAMS or self.azimuth_half

    def apply(self, points: np.ndarray) -> np.ndarray:
        """The kept points `(m, C)` of one scan `points (n, C)`."""
        return thin_beams(points, self.beams, self.azimuth_half)

    def sensor(self, sensor: str) -> str:
        """The profile to record: the [kitti] profile's thinned twin `kitti-<beams>[-half]`
        (sensors.toml) when thinning the default `kitti`; any other profile as given."""
        if not self.active or sensor != "kitti":
            return sensor
        return f"kitti-{self.beams}" + ("-half" if self.azimuth_half else "")

    def params(self) -> dict:
        """Manifest parameters: none when every point is kept (so that imports made before
        the option existed stay up to date)."""
        if not self.active:
            return {}
        return {"beams": self.beams, "beams_azimuth_half": self.azimuth_half}

    def notes(self) -> list[str]:
        if not self.active:
            return []
        step = SCAN_BEAMS // self.beams
        half = "; every 2nd point of each kept beam along azimuth" if self.azimuth_half else ""
        return [
            f"beams: {self.beams} of {SCAN_BEAMS} (k-means of each scan's elevation angles, "
            f"beams 0, {step}, {2 * step}, ... from the lowest kept{half})"
        ]
