"""Scene layout: a street in a road frame (u along the road, v to the left) turned by the road
heading: a road with lanes and curbs, sidewalks, building walls with gaps, poles, trees and
bushes, car-sized containers, an optional cross street, and 5-30 cars (driving in lanes, parked
along the curbs or in rows off the road) that never overlap each other or the clutter; a sloped,
slightly rough ground through z = -mount_height under the sensor."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from dali_cli.geometry import bev_corners, footprints_overlap, rotate_xy, wrap_angle
from dali_cli.sensors import SensorProfile
from dali_cli.world.cars import POOL_SIZE, sample_car_sizes

MIN_CARS, MAX_CARS = 5, 30
MIN_RANGE_M, MAX_RANGE_M = 3.0, 80.0
EGO_FOOTPRINT = np.array([0.0, 0.0, 0.0, 5.2, 2.6, 1.6, 0.0])  # the sensor's own car, with margin


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
        boxes[:, :2] = rotate_xy(boxes[:, :2], heading)
        boxes[:, 6] = wrap_angle(boxes[:, 6] + heading)
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
        vertices[:, :2] = rotate_xy(vertices[:, :2], heading)
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
