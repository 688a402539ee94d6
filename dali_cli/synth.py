"""Synthetic labeled LiDAR frames: street scenes of procedural cars and clutter, scanned by a sensor profile.

A scene is laid out in a road frame (u along the road, v to the left) and turned by the road
heading: a road with lanes and curbs, sidewalks, building walls with gaps, poles, trees and bushes,
car-sized containers, an optional cross street, and 5-30 cars (driving in lanes, parked along the
curbs or in rows off the road) that never overlap each other or the clutter. Car sizes are drawn
around the `cars` profile's mean l/w/h with its spread; each car is a model from a fixed pool of
procedural cars (seeds disjoint from `dali library build --procedural`), scaled into its box.

The scan casts every ray of the sensor pattern: the ground (a sloped, slightly rough height field
through z = -mount_height under the sensor) is intersected analytically; clutter is one Embree
scene per frame; each car is traced with rays moved into its cached model BVH, only for the rays
in the car's angular window. The first hit wins, so cars occlude each other and clutter occludes
cars. Then range noise, ray dropout, min/max range, and intensity from incidence and material.

Everything random comes from (seed, frame index), so frame k is the same whatever the number of
frames, their order or the worker count.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from dali_cli.library import normalize_mesh
from dali_cli.procedural import generate_car_mesh
from dali_cli.raycast import Scene, cast, cast_into_box
from dali_cli.sensors import SensorProfile

POOL_SALT = 0x5EED_CA25  # the synthetic car pool's seed space (library cars use [seed, i])
POOL_SIZE = 64
POOL_LOD = 6000
FRAME_SALT = 0x53594E54
MIN_CARS, MAX_CARS = 5, 30
MIN_RANGE_M, MAX_RANGE_M = 3.0, 80.0
SIZE_CORRELATION = 0.6  # cars that are long tend to be wide and tall too
EGO_FOOTPRINT = np.array([0.0, 0.0, 0.0, 5.2, 2.6, 1.6, 0.0])  # the sensor's own car, with margin


# ---------------------------------------------------------------------------------------------
# The car pool


@dataclass(frozen=True)
class PoolCar:
    """One synthetic car model: unit-box mesh, kind, glass starts above `beltline_unit` (unit z)."""

    vertices: np.ndarray
    faces: np.ndarray
    kind: str
    beltline_unit: float

    def bvh(self):
        from dali_cli.raycast import get_bvh

        return get_bvh(self.vertices, self.faces)


@lru_cache(maxsize=POOL_SIZE)
def pool_car(index: int) -> PoolCar:
    """Model `index` of the synthetic pool (built once per process)."""
    vertices, faces, shape = generate_car_mesh([POOL_SALT, int(index)], lod=POOL_LOD)
    unit, faces, native = normalize_mesh(vertices, faces, f"synth-pool-{index}")
    return PoolCar(unit, faces, shape.kind, float(shape.beltline / native[2] - 0.5))


# ---------------------------------------------------------------------------------------------
# Geometry helpers


def _rotate(xy: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], axis=-1)


def _wrap(angle):
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def bev_corners(boxes: np.ndarray) -> np.ndarray:
    """Footprint corners `(N, 4, 2)` (counter-clockwise) of boxes `(N, 7)`."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    signs = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])
    local = signs[None] * boxes[:, None, 3:5]  # (N, 4, 2)
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    x = c * local[..., 0] - s * local[..., 1] + boxes[:, None, 0]
    y = s * local[..., 0] + c * local[..., 1] + boxes[:, None, 1]
    return np.stack([x, y], axis=-1)


def footprints_overlap(candidate: np.ndarray, others: np.ndarray) -> np.ndarray:
    """Separating-axis test of one footprint `(4, 2)` against many `(M, 4, 2)` → `(M,)` bool."""
    if len(others) == 0:
        return np.zeros(0, bool)
    cand_edges = np.diff(candidate[[0, 1, 2]], axis=0)  # (2, 2)
    other_edges = others[:, 1:3] - others[:, 0:2]  # (M, 2, 2)
    axes = np.concatenate([np.broadcast_to(cand_edges, other_edges.shape), other_edges], axis=1)
    axes = np.stack([-axes[..., 1], axes[..., 0]], axis=-1)  # (M, 4, 2) edge normals
    project_candidate = np.einsum("mak,ck->mac", axes, candidate)  # (M, 4, 4)
    project_others = np.einsum("mak,mck->mac", axes, others)  # (M, 4, 4)
    separated = (project_candidate.max(-1) < project_others.min(-1)) | (
        project_others.max(-1) < project_candidate.min(-1)
    )
    return ~separated.any(axis=1)


@dataclass(frozen=True)
class Ground:
    """z = -mount + a x + b y + sum_k amp_k (sin(k_k . (x, y) + phase_k) - sin(phase_k)) (metres).

    The correction term makes z(0, 0) = -mount_height exactly under the sensor.
    """

    mount_height_m: float
    slope: np.ndarray  # (2,) dz/dx, dz/dy
    wave_vectors: np.ndarray  # (K, 2) rad/m
    amplitudes: np.ndarray  # (K,) m
    phases: np.ndarray  # (K,)

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground z at positions `(N,)`, `(N,)` → `(N,)`.

        Written with broadcasting, not `@`: BLAS calls with an inner size of 2 or 3 are slow and
        spawn threads.
        """
        angle = (
            x[:, None] * self.wave_vectors[:, 0]
            + y[:, None] * self.wave_vectors[:, 1]
            + self.phases
        )
        rough = ((np.sin(angle) - np.sin(self.phases)) * self.amplitudes).sum(axis=1)  # (N,)
        return -self.mount_height_m + self.slope[0] * x + self.slope[1] * y + rough

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground z at `(..., 2)` positions → `(...)`."""
        xy = np.asarray(xy, np.float64)
        flat = xy.reshape(-1, 2)
        return self.height_at(flat[:, 0], flat[:, 1]).reshape(xy.shape[:-1])

    def normal(self) -> np.ndarray:
        """Unit normal `(3,)` of the mean plane (roughness is too small to matter for intensity)."""
        normal = np.array([-self.slope[0], -self.slope[1], 1.0])
        return normal / np.linalg.norm(normal)

    def intersect(self, directions: np.ndarray, max_t: float) -> np.ndarray:
        """Ray parameter of the ground hit of rays from the origin `(N, 3)` → `(N,)`, inf on a miss.

        The mean-plane solution plus one step that puts the point on the rough surface (the
        roughness is centimetres over metres of wavelength: the step error is far below the
        range noise except at grazing angles, where it only moves a point along its own ray).
        """
        dx, dy, dz = directions[:, 0], directions[:, 1], directions[:, 2]
        rate = dz - self.slope[0] * dx - self.slope[1] * dy  # dz/dt of the ray above the plane
        candidate = np.flatnonzero(rate < -1e-6)
        rate = rate[candidate]
        t = -self.mount_height_m / rate
        near = t < 1.5 * max_t
        candidate, t, rate = candidate[near], t[near], rate[near]
        z = self.height_at(t * dx[candidate], t * dy[candidate])
        t = t - (t * dz[candidate] - z) / rate
        distance = np.full(len(directions), np.inf)
        good = (t > 0) & (t <= max_t)
        distance[candidate[good]] = t[good]
        return distance


# ---------------------------------------------------------------------------------------------
# Clutter meshes (small, in metres, placed in the sensor frame)

_BOX_FACES = np.array(
    [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
     [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]]
)  # fmt: skip


def _box_mesh(box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A box `(7,)` as 8 vertices and 12 triangles."""
    corners = bev_corners(box)[0]  # (4, 2)
    bottom = box[2] - box[5] / 2
    vertices = np.concatenate(
        [np.c_[corners, np.full(4, bottom)], np.c_[corners, np.full(4, bottom + box[5])]]
    )
    return vertices, _BOX_FACES


def _cylinder_mesh(x: float, y: float, z0: float, radius: float, height: float, sections: int = 8):
    angle = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    ring = np.c_[x + radius * np.cos(angle), y + radius * np.sin(angle)]
    vertices = np.concatenate(
        [np.c_[ring, np.full(sections, z0)], np.c_[ring, np.full(sections, z0 + height)]]
    )
    k = np.arange(sections)
    n = (k + 1) % sections
    sides = np.concatenate(
        [np.stack([k, n, sections + n], 1), np.stack([k, sections + n, sections + k], 1)]
    )
    top = np.stack([np.full(sections - 2, sections), sections + k[1:-1], sections + k[2:]], 1)
    return vertices, np.concatenate([sides, top])


@lru_cache(maxsize=1)
def _unit_sphere() -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2)
    return np.asarray(sphere.vertices), np.asarray(sphere.faces)


def _blob_mesh(center: np.ndarray, radii: np.ndarray, rng: np.random.Generator):
    """A lumpy ellipsoid (vegetation) around `center` (3,) with `radii` (3,)."""
    vertices, faces = _unit_sphere()
    lumps = 1.0 + 0.18 * np.sin(vertices @ rng.normal(0, 3.0, (3, 3))).sum(axis=1) / 3.0
    return center + vertices * radii * lumps[:, None], faces


# ---------------------------------------------------------------------------------------------
# Scenes


@dataclass
class SynthScene:
    """One generated scene in the sensor frame.

    cars: `(K, 7)` boxes (geometric center, ground-standing); car_models `(K,)` pool indices;
    car_reflectance `(K,)`; clutter: vertices `(V, 3)`, faces `(F, 3)`, face_reflectance `(F,)`;
    road: heading (rad) and lane-marking lateral offsets (m, road frame) for ground intensity.
    """

    ground: Ground
    cars: np.ndarray
    car_models: np.ndarray
    car_reflectance: np.ndarray
    clutter_vertices: np.ndarray
    clutter_faces: np.ndarray
    face_reflectance: np.ndarray
    road_heading: float
    lane_lines: np.ndarray


def sample_car_sizes(
    rng: np.random.Generator, count: int, mean: np.ndarray, std: np.ndarray
) -> np.ndarray:
    """`(count, 3)` l, w, h around `mean` with spread `std`, correlated, clipped at 2.5 sigma."""
    common = rng.standard_normal((count, 1))
    own = rng.standard_normal((count, 3))
    z = SIZE_CORRELATION * common + np.sqrt(1 - SIZE_CORRELATION**2) * own
    return np.asarray(mean) + np.asarray(std) * np.clip(z, -2.5, 2.5)


class _Layout:
    """Footprints placed so far (ego road frame), for overlap checks."""

    def __init__(self):
        self.corners = np.zeros((0, 4, 2))
        self.centers = np.zeros((0, 2))
        self.radii = np.zeros(0)

    def free(self, box: np.ndarray, margin: float) -> bool:
        grown = np.array(box, np.float64)
        grown[3:5] += 2 * margin
        radius = 0.5 * np.hypot(grown[3], grown[4])
        # only footprints whose bounding circles meet need the separating-axis test
        close = np.hypot(*(self.centers - grown[:2]).T) < self.radii + radius
        return not footprints_overlap(bev_corners(grown)[0], self.corners[close]).any()

    def add(self, box: np.ndarray) -> None:
        box = np.asarray(box, np.float64)
        self.corners = np.concatenate([self.corners, bev_corners(box)])
        self.centers = np.concatenate([self.centers, box[None, :2]])
        self.radii = np.append(self.radii, 0.5 * np.hypot(box[3], box[4]))


def generate_scene(
    rng: np.random.Generator, sensor: SensorProfile, cars: SensorProfile
) -> SynthScene:
    """Lay out one street scene (see module docstring)."""
    mount = sensor.mount_height_m
    reach = min(MAX_RANGE_M, sensor.max_range_m) + 10.0  # clutter beyond this is never seen
    ground = Ground(
        mount_height_m=mount,
        slope=rng.normal(0.0, 0.004, 2).clip(-0.012, 0.012),
        wave_vectors=rng.normal(0.0, 1.0, (3, 2)) * (2 * np.pi / rng.uniform(3.0, 25.0, (3, 1))),
        amplitudes=rng.uniform(0.003, 0.012, 3),
        phases=rng.uniform(0, 2 * np.pi, 3),
    )
    heading = float(rng.normal(0.0, 0.06))
    lanes_per_side = int(rng.integers(1, 3))
    lane = rng.uniform(3.2, 3.7)
    road_half = lanes_per_side * lane + rng.uniform(0.0, 2.5)  # + parking strip
    ego_v = -rng.uniform(0.3, 0.7) * lane  # the ego drives in a right-hand lane
    sidewalk = rng.uniform(2.0, 5.0)
    cross = rng.random() < 0.45
    cross_u = float(rng.choice([-1, 1]) * rng.uniform(15.0, 50.0)) if cross else np.inf
    cross_half = rng.uniform(4.0, 8.0)

    layout = _Layout()
    layout.add(EGO_FOOTPRINT)
    # everything below is in the ego road frame: u along the road, v lateral from the ego
    meshes: list[tuple[np.ndarray, np.ndarray, float]] = []
    static_boxes: list[tuple[np.ndarray, float]] = []

    def lateral(v_road: float) -> float:
        return float(v_road - ego_v)

    def on_cross(u: np.ndarray | float, half: float = 0.0) -> bool:
        return bool(np.abs(np.asarray(u) - cross_u).min() < cross_half + half)

    # curbs along both road edges in short segments (they follow the sloped ground)
    for side in (-1, 1):
        height = rng.uniform(0.12, 0.18)
        for u0 in np.arange(-reach, reach, 8.0):
            if not on_cross(np.array([u0, u0 + 8.0])) and not on_cross(u0 + 4.0, 4.0):
                curb = np.array([u0 + 4.0, lateral(side * road_half), 0, 8.0, 0.25, height, 0])
                static_boxes.append((curb, 1.0))
    # building walls behind the sidewalks, in segments with gaps
    for side in (-1, 1):
        if rng.random() < 0.25:
            continue
        setback = road_half + sidewalk + rng.uniform(0.0, 6.0)
        u = -reach
        while u < reach:
            length = rng.uniform(8.0, 40.0)
            center = u + length / 2
            if not on_cross(center, length / 2 + 1.0):
                thickness = rng.uniform(0.4, 1.0)
                v = lateral(side * (setback + thickness / 2 + rng.uniform(0.0, 1.5)))
                wall = np.array([center, v, 0, length, thickness, rng.uniform(3.0, 15.0), 0])
                static_boxes.append((wall, rng.uniform(0.6, 1.4)))
                layout.add(wall)
            u += length + (rng.uniform(2.0, 12.0) if rng.random() < 0.5 else 0.3)
    # poles and trees along the sidewalks
    for side in (-1, 1):
        u = -reach + rng.uniform(0, 15)
        while u < reach:
            v = lateral(side * (road_half + rng.uniform(0.4, 1.0)))
            if not on_cross(u, 1.0):
                if rng.random() < 0.55:
                    radius, height = rng.uniform(0.07, 0.2), rng.uniform(3.0, 9.0)
                    pole = np.array([u, v, 0, 2 * radius, 2 * radius, height, 0])
                    if layout.free(pole, 0.3):
                        meshes.append(
                            (
                                *_cylinder_mesh(u, v, -0.5, radius, height + 0.5),
                                rng.uniform(0.8, 1.8),
                            )
                        )
                        layout.add(pole)
                else:
                    trunk = rng.uniform(0.12, 0.3)
                    crown = rng.uniform(1.2, 3.0, 3) * [1, 1, 0.8]
                    tree = np.array([u, v, 0, 2 * trunk, 2 * trunk, 5.0, 0])
                    if layout.free(tree, 0.3):
                        top = rng.uniform(2.5, 4.0)
                        meshes.append(
                            (*_cylinder_mesh(u, v, -0.5, trunk, top + 0.5 + crown[2] * 0.5), 0.7)
                        )
                        meshes.append(
                            (*_blob_mesh(np.array([u, v, top + crown[2]]), crown, rng), 0.45)
                        )
                        layout.add(tree)
            u += rng.uniform(8.0, 30.0)
    for _ in range(int(rng.integers(3, 12))):  # bushes and hedges beside the road
        side = rng.choice([-1, 1])
        u, v = (
            rng.uniform(-reach, reach),
            lateral(side * (road_half + rng.uniform(1.0, sidewalk + 8.0))),
        )
        radii = np.array([rng.uniform(0.5, 3.0), rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.2)])
        bush = np.array([u, v, 0, 2 * radii[0], 2 * radii[1], 2 * radii[2], 0])
        if layout.free(bush, 0.2):
            meshes.append((*_blob_mesh(np.array([u, v, 0.6 * radii[2]]), radii, rng), 0.4))
            layout.add(bush)
    for _ in range(int(rng.integers(0, 4))):  # car-sized containers and kiosks: false-positive bait
        side = rng.choice([-1, 1])
        size = np.array([rng.uniform(2.0, 6.0), rng.uniform(1.4, 2.5), rng.uniform(1.0, 2.6)])
        v = lateral(side * (road_half + sidewalk + rng.uniform(1, 8)))
        box = np.array([rng.uniform(-reach, reach), v, 0, *size, rng.normal(0, 0.1)])
        if layout.free(box, 0.3):
            static_boxes.append((box, rng.uniform(0.6, 1.6)))
            layout.add(box)

    # cars: lanes, curb parking, rows off the road, the cross street
    count = int(rng.integers(MIN_CARS, MAX_CARS + 1))
    sizes = sample_car_sizes(
        rng, count, np.array(cars.car_mean_lwh_m), np.array(cars.car_std_lwh_m)
    )
    placed: list[np.ndarray] = []
    max_center = min(MAX_RANGE_M, sensor.max_range_m + 5.0)
    for size in sizes:
        for _attempt in range(30):
            slot = rng.random()
            side = rng.choice([-1, 1])
            u = rng.uniform(-max_center, max_center)
            if slot < 0.35:  # driving in a lane (right-hand traffic)
                lane_index = int(rng.integers(0, lanes_per_side))
                v = side * (lane_index + 0.5) * lane + rng.normal(0, 0.25)
                yaw = (0.0 if side < 0 else np.pi) + rng.normal(0, 0.03)
            elif slot < 0.75:  # parked along a curb
                v = side * (road_half - size[1] / 2 - rng.uniform(0.1, 0.4))
                yaw = rng.choice([0.0, np.pi]) + rng.normal(0, 0.04)
            elif slot < 0.9:  # rows in a lot beside the road, perpendicular
                v = side * (road_half + sidewalk + size[0] / 2 + rng.uniform(0.5, 6.0))
                yaw = rng.choice([np.pi / 2, -np.pi / 2]) + rng.normal(0, 0.06)
            elif cross:  # on the cross street
                u = cross_u + rng.uniform(-0.6, 0.6) * cross_half
                v = rng.uniform(-max_center, max_center)
                yaw = rng.choice([np.pi / 2, -np.pi / 2]) + rng.normal(0, 0.04)
            else:  # anywhere off the road at a random angle
                v = side * (road_half + rng.uniform(1.0, 30.0))
                yaw = rng.uniform(-np.pi, np.pi)
            v = lateral(v)
            if not MIN_RANGE_M <= np.hypot(u, v) <= max_center:
                continue
            box = np.array([u, v, 0.0, *size, yaw])
            if layout.free(box, 0.25):
                layout.add(box)
                placed.append(box)
                break

    # ego road frame -> sensor frame: turn by the road heading, stand everything on the ground
    def to_sensor(boxes: np.ndarray) -> np.ndarray:
        boxes = np.array(boxes, np.float64).reshape(-1, 7)
        boxes[:, :2] = _rotate(boxes[:, :2], heading)
        boxes[:, 6] = _wrap(boxes[:, 6] + heading)
        return boxes

    car_boxes = to_sensor(np.array(placed).reshape(-1, 7))
    car_boxes[:, 2] = ground.height(car_boxes[:, :2]) + car_boxes[:, 5] / 2
    clutter_v, clutter_f, clutter_r = [], [], []
    offset = 0
    for box, reflect in static_boxes:
        box = to_sensor(box)[0]
        sink = 0.5 if box[5] > 1.0 else 0.03  # buried a little so slopes leave no gap
        base = ground.height(box[:2]) - sink
        box[5] += sink
        box[2] = base + box[5] / 2
        vertices, faces = _box_mesh(box)
        clutter_v.append(vertices)
        clutter_f.append(faces + offset)
        clutter_r.append(np.full(len(faces), reflect))
        offset += len(vertices)
    for vertices, faces, reflect in meshes:
        vertices = vertices.copy()
        vertices[:, :2] = _rotate(vertices[:, :2], heading)
        vertices[:, 2] += ground.height(vertices[:, :2].mean(axis=0))
        clutter_v.append(vertices)
        clutter_f.append(faces + offset)
        clutter_r.append(np.full(len(faces), reflect))
        offset += len(vertices)
    lane_lines = np.arange(-lanes_per_side + 1, lanes_per_side) * lane - ego_v  # ego-lateral
    return SynthScene(
        ground=ground,
        cars=car_boxes,
        car_models=rng.integers(0, POOL_SIZE, len(car_boxes)),
        car_reflectance=rng.uniform(0.5, 1.7, len(car_boxes)),
        clutter_vertices=np.concatenate(clutter_v),
        clutter_faces=np.concatenate(clutter_f).astype(np.int32),
        face_reflectance=np.concatenate(clutter_r),
        road_heading=heading,
        lane_lines=lane_lines,
    )


# ---------------------------------------------------------------------------------------------
# Scanning


@dataclass(frozen=True)
class _Pattern:
    directions: np.ndarray  # (B * P, 3) float64 unit, beam-major
    directions32: np.ndarray  # the same as float32 C-contiguous (Embree's input, no copy)
    elevations: np.ndarray  # (B,) ascending rad
    azimuth_start: float
    azimuth_step: float
    columns: int
    full_circle: bool


@lru_cache(maxsize=8)
def _pattern(sensor: SensorProfile) -> _Pattern:
    return _Pattern(
        directions=sensor.ray_pattern().directions.astype(np.float64),
        directions32=sensor.ray_pattern().directions,
        elevations=sensor.elevations_rad(),
        azimuth_start=float(np.radians(sensor.azimuth_min_deg)),
        azimuth_step=sensor.azimuth_step_rad,
        columns=sensor.points_per_beam,
        full_circle=sensor.azimuth_max_deg - sensor.azimuth_min_deg >= 360.0 - 1e-9,
    )


def box_ray_window(pattern: _Pattern, box: np.ndarray) -> np.ndarray:
    """Indices `(R,)` int64 of the pattern rays that can hit `box` (7,) seen from the origin.

    Azimuth bounds from the footprint corners; elevation bounds from the nearest and farthest
    footprint points (a box's top edge seen side-on peaks between corners), one ray of margin.
    """
    corners = bev_corners(box)[0]
    center_azimuth = np.arctan2(box[1], box[0])
    offsets = _wrap(np.arctan2(corners[:, 1], corners[:, 0]) - center_azimuth)
    # azimuth of the center counted from the pattern's first column, in [0, 2 pi)
    relative = np.mod(center_azimuth - pattern.azimuth_start, 2.0 * np.pi)
    low = int(np.floor((relative + offsets.min()) / pattern.azimuth_step)) - 1
    high = int(np.ceil((relative + offsets.max()) / pattern.azimuth_step)) + 1
    columns = np.arange(low, high + 1)
    if pattern.full_circle:
        columns = np.unique(columns % pattern.columns)
    else:  # a partial field of view: the box may also straddle its start, one turn earlier
        turn = int(round(2.0 * np.pi / pattern.azimuth_step))
        columns = np.concatenate([columns, columns - turn])
        columns = np.unique(columns[(columns >= 0) & (columns < pattern.columns)])
    c, s = np.cos(box[6]), np.sin(box[6])
    local = np.array(
        [-(c * box[0] + s * box[1]), -(-s * box[0] + c * box[1])]
    )  # sensor in box frame
    gap = np.maximum(np.abs(local) - box[3:5] / 2, 0.0)
    near = max(float(np.hypot(*gap)), 1e-3)
    far = float(np.linalg.norm(corners, axis=1).max())
    top, bottom = box[2] + box[5] / 2, box[2] - box[5] / 2
    high_elevation = np.arctan2(top, near if top > 0 else far)
    low_elevation = np.arctan2(bottom, near if bottom < 0 else far)
    beam_low = max(int(np.searchsorted(pattern.elevations, low_elevation)) - 1, 0)
    beam_high = min(
        int(np.searchsorted(pattern.elevations, high_elevation)) + 1, len(pattern.elevations) - 1
    )
    beams = np.arange(beam_low, beam_high + 1)
    return (beams[:, None] * pattern.columns + columns[None, :]).reshape(-1)


@dataclass
class Scan:
    """A scanned frame: points `(n, 4)` float32, owner `(n,)` int32 (car index, -1 ground, -2
    clutter), and per car: visible rays before dropout `(K,)`, unoccluded rays `(K,)`."""

    points: np.ndarray
    owner: np.ndarray
    car_visible_rays: np.ndarray
    car_unoccluded_rays: np.ndarray


def scan_scene(
    scene: SynthScene, sensor: SensorProfile, rng: np.random.Generator, threads: int = 1
) -> Scan:
    """First-hit scan of `scene` with the full pattern of `sensor` (see module docstring)."""
    pattern = _pattern(sensor)
    directions = pattern.directions  # (R, 3)
    count = len(directions)
    limit = sensor.max_range_m + 4.0 * sensor.range_noise_sigma_m + 0.5
    distance = scene.ground.intersect(directions, limit)  # (R,)
    owner = np.where(np.isfinite(distance), -1, -3).astype(np.int32)  # -3: no return
    cosine = np.zeros(count)
    reflect = np.zeros(count)

    static = Scene([(scene.clutter_vertices, scene.clutter_faces)])
    hits = cast(
        static,
        np.zeros(3),
        pattern.directions32,
        max_distance=np.minimum(distance, limit),
        threads=threads,
    )
    closer = hits.hit & (hits.distance < distance)
    distance[closer] = hits.distance[closer]
    owner[closer] = -2
    cosine[closer] = hits.cosine_incidence(directions)[closer]
    reflect[closer] = scene.face_reflectance[hits.primitive_id[closer]] * sensor.intensity_clutter

    unoccluded = np.zeros(len(scene.cars), np.int64)
    for k, box in enumerate(scene.cars):
        rays = box_ray_window(pattern, box)
        if len(rays) == 0:
            continue
        model = pool_car(int(scene.car_models[k]))
        car = cast_into_box(
            model.bvh(), np.zeros(3), directions[rays], box, max_distance=limit, threads=threads
        )
        unoccluded[k] = int(car.hit.sum())
        win = car.hit & (car.distance < distance[rays])
        chosen = rays[win]
        distance[chosen] = car.distance[win]
        owner[chosen] = k
        cosine[chosen] = car.cosine_incidence(directions[rays])[win]
        # glass above the beltline returns less
        local_z = (car.points[win, 2] - box[2]) / box[5]
        glass = np.where(local_z > model.beltline_unit, 0.35, 1.0)
        reflect[chosen] = scene.car_reflectance[k] * sensor.intensity_car * glass

    ground = owner == -1
    if ground.any():
        xy = distance[ground, None] * directions[ground, :2]
        normal = scene.ground.normal()
        cosine[ground] = np.abs((directions[ground] * normal).sum(axis=1))
        lateral = _rotate(xy, -scene.road_heading)[:, 1]
        along = _rotate(xy, -scene.road_heading)[:, 0]
        marking = np.zeros(len(xy), bool)
        if len(scene.lane_lines):
            near_line = np.abs(lateral[:, None] - scene.lane_lines[None, :]).min(axis=1) < 0.08
            marking = near_line & ((along % 9.0) < 3.0)  # dashed lines
        reflect[ground] = sensor.intensity_ground * np.where(marking, 4.0, 1.0)

    visible = np.bincount(owner[owner >= 0], minlength=len(scene.cars))
    returned = owner != -3
    noisy = distance + rng.normal(0.0, sensor.range_noise_sigma_m, count)
    keep = returned & (rng.random(count) >= sensor.ray_dropout)
    keep &= (noisy >= sensor.min_range_m) & (noisy <= sensor.max_range_m)
    intensity = reflect * (0.25 + 0.75 * cosine) + rng.normal(0.0, 0.02, count)
    points = np.c_[noisy[keep, None] * directions[keep], np.clip(intensity[keep], 0.0, 1.0)]
    return Scan(
        points=points.astype(np.float32),
        owner=owner[keep],
        car_visible_rays=visible,
        car_unoccluded_rays=unoccluded,
    )


# ---------------------------------------------------------------------------------------------
# Frames


def frame_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of frame `index` of a run with `seed` (independent of everything else)."""
    return np.random.default_rng(
        np.random.SeedSequence([FRAME_SALT, int(seed) & 0xFFFFFFFF, int(index)])
    )


def frame_id(index: int) -> str:
    return f"{int(index):06d}"


@dataclass
class SynthFrame:
    """One frame: points `(n, 4)` float32 and labels of the cars with >= 1 point.

    boxes `(K, 7)`, num_points `(K,)` int32, occlusion `(K,)` float32 (share of the car's
    unoccluded rays that something else blocked), kind `(K,)` str, model `(K,)` int32 pool index.
    owner `(n,)` int32: label row of each point (-1 ground, -2 clutter).
    """

    frame_id: str
    points: np.ndarray
    boxes: np.ndarray
    num_points: np.ndarray
    occlusion: np.ndarray
    kind: np.ndarray
    model: np.ndarray
    owner: np.ndarray


def synth_frame(
    seed: int, index: int, sensor: SensorProfile, cars: SensorProfile, threads: int = 1
) -> SynthFrame:
    """Generate and scan frame `index` of a run with `seed` (deterministic per (seed, index))."""
    rng = frame_rng(seed, index)
    scene = generate_scene(rng, sensor, cars)
    scan = scan_scene(scene, sensor, rng, threads=threads)
    counts = np.bincount(scan.owner[scan.owner >= 0], minlength=len(scene.cars))
    labeled = np.flatnonzero(counts >= 1)
    row_of_car = np.full(
        len(scene.cars) + 3, -1, np.int64
    )  # indices -3..-1 map to themselves below
    row_of_car[labeled] = np.arange(len(labeled))
    owner = np.where(scan.owner >= 0, row_of_car[np.maximum(scan.owner, 0)], scan.owner).astype(
        np.int32
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        occlusion = 1.0 - scan.car_visible_rays / scan.car_unoccluded_rays
    occlusion = np.clip(np.nan_to_num(occlusion, nan=1.0), 0.0, 1.0)
    models = scene.car_models[labeled]
    return SynthFrame(
        frame_id=frame_id(index),
        points=scan.points,
        boxes=scene.cars[labeled],
        num_points=counts[labeled].astype(np.int32),
        occlusion=occlusion[labeled].astype(np.float32),
        kind=np.array([pool_car(int(m)).kind for m in models], dtype=object),
        model=models.astype(np.int32),
        owner=owner,
    )


# ---------------------------------------------------------------------------------------------
# The stage


def iter_frames(
    seed: int, frames: range | int, sensor: SensorProfile, cars: SensorProfile, threads: int = 1
):
    """Yield SynthFrames of `frames` (a range of indices, or 0..frames-1) in order, each traced
    with `threads` Embree threads, in this process (the serial path; see SynthShards)."""
    indices = range(int(frames)) if isinstance(frames, int) else frames
    for index in indices:
        yield synth_frame(int(seed), index, sensor, cars, threads=int(threads))


def frame_table(frame: SynthFrame):
    """One frame's labels as a BoxTable: every car with >= 1 point, its KITTI label fields."""
    from dali_cli.artifacts import BoxTable
    from dali_cli.camera import kitti_label_columns

    return BoxTable.from_arrays(
        np.full(len(frame.boxes), frame.frame_id, dtype=object),
        frame.boxes,
        label="Car",
        num_points=frame.num_points,
        occlusion=frame.occlusion,
        kind=frame.kind.astype(str),
        car_model=frame.model,
        # after the scan, from the boxes alone: no random draw, points unchanged
        **kitti_label_columns(frame.boxes, frame.occlusion),
    )


@dataclass(frozen=True)
class SynthShards:
    """Worker factory and worker of the sharded path (dali_cli.executors): a shard's frames
    and labels, written as shard files (points) and boxes.parquet. Nothing to load."""

    seed: int
    sensor: SensorProfile
    cars: SensorProfile
    threads: int = 1

    def __call__(self) -> SynthShards:
        return self

    def run(self, shard, directory: Path) -> dict:
        from dali_cli.artifacts import BoxTable, write_boxes
        from dali_cli.executors import naming_frames
        from dali_cli.executors.shards import ShardFramesWriter

        writer, tables = ShardFramesWriter(directory), []
        for index in range(shard.start, shard.stop):
            with naming_frames(frame_id(index)):
                frame = synth_frame(self.seed, index, self.sensor, self.cars, self.threads)
            writer.append(frame.frame_id, frame.points)
            tables.append(frame_table(frame))
        points = writer.close()
        write_boxes(directory, BoxTable.concat(tables))
        return {"points": points}


def build_synth(
    out_dir,
    sensor: SensorProfile,
    cars: SensorProfile,
    frames: int,
    seed: int,
    progress: bool = True,
    threads: int = 1,
    executor=None,
):
    """Write `frames` synthetic frames as a FrameSet + boxes.parquet into `out_dir`, in this
    process or, given a parallel `executor` (dali_cli.executors), as shards on its workers
    merged in order (the same bytes).

    Returns a manifest.BuildResult with counts (frames, points, labels, mean label size, points
    per car by range band) and timings.
    """
    import time

    from tqdm import tqdm

    from dali_cli.artifacts import BoxTable, FrameSetWriter, read_boxes, write_boxes
    from dali_cli.manifest import BuildResult

    started = time.perf_counter()
    attrs = {
        "synthetic": True,
        "cars_profile": cars.name,
        "seed": int(seed),
        "mount_height_m": sensor.mount_height_m,
    }
    tables, total_points = [], 0
    bar = tqdm(total=frames, desc=f"synth {sensor.name}", unit="frame", disable=not progress)
    with FrameSetWriter(out_dir, sensor.name, attrs) as writer:
        if executor is None or executor.serial:
            for frame in iter_frames(seed, frames, sensor, cars, threads):
                writer.append(frame.frame_id, frame.points)
                total_points += len(frame.points)
                tables.append(frame_table(frame))
                bar.update(1)
        else:
            from dali_cli.executors import plan_shards, shard_results
            from dali_cli.executors.shards import read_shard_frames

            ids = [frame_id(index) for index in range(frames)]
            worker = SynthShards(int(seed), sensor, cars, int(threads))
            shards = plan_shards(ids, executor.workers, max_frames=16)
            for shard, directory, _ in shard_results(executor, worker, shards, Path(out_dir)):
                for name, points in read_shard_frames(directory):
                    writer.append(name, points)
                    total_points += len(points)
                tables.append(read_boxes(directory))
                bar.update(len(shard.frame_ids))
    bar.close()
    table = BoxTable.concat(tables)
    write_boxes(out_dir, table)
    elapsed = time.perf_counter() - started
    lwh = table.boxes[:, 3:6] if len(table) else np.zeros((0, 3))
    distance = np.hypot(table["x"], table["y"]) if len(table) else np.zeros(0)
    bands = {}
    for low, high in ((0, 30), (30, 50), (50, 80)):
        inside = (distance >= low) & (distance < high)
        bands[f"{low}-{high}m"] = (
            float(np.mean(table["num_points"][inside])) if inside.any() else 0.0
        )
    counts = {
        "frames": int(frames),
        "points": int(total_points),
        "labels": len(table),
        "labels_per_frame": round(len(table) / max(frames, 1), 2),
        "mean_label_lwh_m": [round(float(v), 3) for v in lwh.mean(axis=0)] if len(lwh) else None,
        "mean_points_per_car_by_range": {k: round(v, 1) for k, v in bands.items()},
    }
    timings = {"frames_per_second": round(frames / max(elapsed, 1e-9), 2)}
    notes = [
        "synthetic street scenes: procedural cars (pool seeds disjoint from `dali library build`), "
        "walls, poles, trees, bushes, curbs, containers; first-hit scan with range noise, dropout "
        "and max range; labels for every car with >= 1 point",
        "occlusion = share of a car's rays blocked by something nearer (0 = fully visible)",
        "KITTI label fields (truncated, occluded level, alpha, bbox_*) from a virtual KITTI left "
        "colour camera at the sensor (dali_cli.camera), so `dali eval --protocol kitti` gives "
        "easy/moderate/hard",
    ]
    extra = {"executor": executor.report()} if executor is not None else {}
    return BuildResult(counts=counts, timings=timings, notes=notes, extra=extra)
