"""Scene layout: a street in a road frame (u along the road, v to the left) turned by the road
heading: a road with lanes, raised sidewalks, building walls with gaps, fences and hedges, poles,
trees and bushes, car-sized containers, an optional cross street, and 2-13 cars (driving in
lanes, parked along the curbs or in rows off the road, nearer ones more often) that never overlap each other or the clutter; a sloped,
slightly rough ground through z = -mount_height under the sensor."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from dali_cli.geometry import bev_corners, footprints_overlap, rotate_xy, wrap_angle
from dali_cli.sensors import SensorProfile
from dali_cli.world.cars import POOL_SIZE, sample_car_sizes

MIN_CARS, MAX_CARS = 2, 15
MIN_RANGE_M, MAX_RANGE_M = 3.0, 80.0
NEAR_BIAS = 2.3  # car positions along the road: |u| = max * U^NEAR_BIAS
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


@dataclass(frozen=True)
class _Street:
    """The road of one scene, in the ego road frame (u along the road, v lateral)."""

    reach: float  # clutter beyond this (m) is never seen
    heading: float  # road heading in the sensor frame (rad)
    lanes_per_side: int
    lane: float
    road_half: float  # half road width incl. the parking strip
    ego_v: float  # the ego's lateral position (a right-hand lane)
    sidewalk: float
    cross: bool
    cross_u: float
    cross_half: float

    def lateral(self, v_road: float) -> float:
        return float(v_road - self.ego_v)

    def on_cross(self, u: np.ndarray | float, half: float = 0.0) -> bool:
        return bool(np.abs(np.asarray(u) - self.cross_u).min() < self.cross_half + half)


def _ground_and_street(rng: np.random.Generator, sensor: SensorProfile) -> tuple[Ground, _Street]:
    """The scene's ground and road, drawn in this order from `rng`."""
    ground = Ground(
        mount_height_m=sensor.mount_height_m,
        slope=rng.normal(0.0, 0.01, 2).clip(-0.03, 0.03),
        wave_vectors=rng.normal(0.0, 1.0, (3, 2)) * (2 * np.pi / rng.uniform(3.0, 25.0, (3, 1))),
        amplitudes=rng.uniform(0.003, 0.012, 3),
        phases=rng.uniform(0, 2 * np.pi, 3),
    )
    heading = float(rng.normal(0.0, 0.06))
    lanes_per_side = 1 if rng.random() < 0.7 else 2
    lane = rng.uniform(3.2, 3.7)
    road_half = lanes_per_side * lane + rng.uniform(0.0, 2.5)  # + parking strip
    ego_v = -rng.uniform(0.3, 0.7) * lane  # the ego drives in a right-hand lane
    sidewalk = rng.uniform(2.0, 4.0)
    cross = rng.random() < 0.45
    cross_u = float(rng.choice([-1, 1]) * rng.uniform(15.0, 50.0)) if cross else np.inf
    cross_half = rng.uniform(4.0, 8.0)
    reach = min(MAX_RANGE_M, sensor.max_range_m) + 10.0
    street = _Street(
        reach, heading, lanes_per_side, lane, road_half, ego_v, sidewalk, cross, cross_u,
        cross_half,
    )  # fmt: skip
    return ground, street


class _Clutter:
    """What the scene holds besides cars (ego road frame): box-shaped clutter `(7,)` with its
    reflectance, free meshes (vertices, faces, reflectance), and the footprint layout."""

    def __init__(self):
        self.layout = _Layout()
        self.layout.add(EGO_FOOTPRINT)
        self.boxes: list[tuple[np.ndarray, float]] = []
        self.meshes: list[tuple[np.ndarray, np.ndarray, float]] = []


def _add_sidewalks(rng, street: _Street, clutter: _Clutter) -> None:
    """Raised sidewalks (curb height, from the road edge to the lots behind) along both road
    edges in short segments that follow the sloped ground."""
    for side in (-1, 1):
        height = rng.uniform(0.1, 0.18)
        for u0 in np.arange(-street.reach, street.reach, 8.0):
            if not street.on_cross(np.array([u0, u0 + 8.0])) and not street.on_cross(u0 + 4.0, 4.0):
                v = street.lateral(side * (street.road_half + street.sidewalk / 2))
                slab = np.array([u0 + 4.0, v, 0, 8.0, street.sidewalk, height, 0])
                clutter.boxes.append((slab, 1.0))


def _add_walls(rng, street: _Street, clutter: _Clutter) -> None:
    """Building walls behind the sidewalks, in segments with gaps."""
    for side in (-1, 1):
        if rng.random() < 0.05:
            continue
        setback = street.road_half + street.sidewalk + rng.uniform(0.0, 4.0)
        u = -street.reach
        while u < street.reach:
            length = rng.uniform(8.0, 40.0)
            center = u + length / 2
            if not street.on_cross(center, length / 2 + 1.0):
                thickness = rng.uniform(0.4, 1.0)
                v = street.lateral(side * (setback + thickness / 2 + rng.uniform(0.0, 1.5)))
                wall = np.array([center, v, 0, length, thickness, rng.uniform(3.0, 15.0), 0])
                clutter.boxes.append((wall, rng.uniform(0.6, 1.4)))
                clutter.layout.add(wall)
            u += length + (rng.uniform(2.0, 12.0) if rng.random() < 0.3 else 0.3)


def _add_pole(rng, u: float, v: float, clutter: _Clutter) -> None:
    radius, height = rng.uniform(0.07, 0.2), rng.uniform(3.0, 9.0)
    pole = np.array([u, v, 0, 2 * radius, 2 * radius, height, 0])
    if clutter.layout.free(pole, 0.3):
        mesh = _cylinder_mesh(u, v, -0.5, radius, height + 0.5)
        clutter.meshes.append((*mesh, rng.uniform(0.8, 1.8)))
        clutter.layout.add(pole)


def _add_tree(rng, u: float, v: float, clutter: _Clutter) -> None:
    trunk = rng.uniform(0.12, 0.3)
    crown = rng.uniform(1.8, 3.8, 3) * [1, 1, 0.8]
    tree = np.array([u, v, 0, 2 * trunk, 2 * trunk, 5.0, 0])
    if clutter.layout.free(tree, 0.3):
        top = rng.uniform(2.8, 4.5)
        clutter.meshes.append((*_cylinder_mesh(u, v, -0.5, trunk, top + 0.5 + crown[2] * 0.5), 0.7))
        clutter.meshes.append((*_blob_mesh(np.array([u, v, top + crown[2]]), crown, rng), 0.45))
        clutter.layout.add(tree)


def _add_street_ends(rng, street: _Street, clutter: _Clutter) -> None:
    """Where the street bends or ends: building fronts or tree lines across it, 45-85 m ahead
    or behind (each in 40% of the scenes)."""
    for direction in (-1, 1):
        if rng.random() >= 0.4:
            continue
        u = direction * rng.uniform(45.0, 85.0)
        if street.on_cross(u, 5.0):
            continue
        width = 2 * (street.road_half + street.sidewalk) + rng.uniform(10.0, 40.0)
        depth = rng.uniform(1.0, 6.0)
        v = street.lateral(rng.uniform(-5.0, 5.0))
        front = np.array([u + direction * depth / 2, v, 0, depth, width, rng.uniform(4, 15), 0])
        if clutter.layout.free(front, 0.5):
            clutter.boxes.append((front, rng.uniform(0.6, 1.4)))
            clutter.layout.add(front)


def _add_fences_and_hedges(rng, street: _Street, clutter: _Clutter) -> None:
    """Fences and hedges along the outer edge of the sidewalks, in segments (front gardens,
    lots), where nothing stands yet."""
    for side in (-1, 1):
        u = -street.reach + rng.uniform(0.0, 10.0)
        while u < street.reach:
            length = rng.uniform(5.0, 30.0)
            center = u + length / 2
            if rng.random() < 0.6 and not street.on_cross(center, length / 2 + 1.0):
                hedge = rng.random() < 0.5
                thickness = rng.uniform(0.6, 1.4) if hedge else rng.uniform(0.05, 0.15)
                height = rng.uniform(0.8, 2.2) if hedge else rng.uniform(0.9, 2.0)
                v = street.lateral(side * (street.road_half + street.sidewalk - thickness / 2))
                segment = np.array([center, v, 0, length, thickness, height, 0])
                if clutter.layout.free(segment, 0.1):
                    reflect = rng.uniform(0.5, 0.9) if hedge else rng.uniform(0.6, 1.6)
                    clutter.boxes.append((segment, reflect))
                    clutter.layout.add(segment)
            u += length + rng.uniform(1.0, 8.0)


def _add_poles_and_trees(rng, street: _Street, clutter: _Clutter) -> None:
    """Poles and trees along the sidewalks."""
    for side in (-1, 1):
        u = -street.reach + rng.uniform(0, 15)
        while u < street.reach:
            v = street.lateral(side * (street.road_half + rng.uniform(0.4, 1.0)))
            if not street.on_cross(u, 1.0):
                if rng.random() < 0.55:
                    _add_pole(rng, u, v, clutter)
                else:
                    _add_tree(rng, u, v, clutter)
            u += rng.uniform(4.0, 12.0)


def _add_bushes_and_containers(rng, street: _Street, clutter: _Clutter) -> None:
    """Bushes and hedges beside the road; car-sized containers and kiosks (false-positive bait)."""
    road_half, sidewalk, reach = street.road_half, street.sidewalk, street.reach
    for _ in range(int(rng.integers(12, 30))):
        side = rng.choice([-1, 1])
        u, v = (
            rng.uniform(-reach, reach),
            street.lateral(side * (road_half + rng.uniform(1.0, sidewalk + 8.0))),
        )
        radii = np.array([rng.uniform(0.5, 3.0), rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.2)])
        bush = np.array([u, v, 0, 2 * radii[0], 2 * radii[1], 2 * radii[2], 0])
        if clutter.layout.free(bush, 0.2):
            clutter.meshes.append((*_blob_mesh(np.array([u, v, 0.6 * radii[2]]), radii, rng), 0.4))
            clutter.layout.add(bush)
    for _ in range(int(rng.integers(0, 4))):
        side = rng.choice([-1, 1])
        size = np.array([rng.uniform(2.0, 6.0), rng.uniform(1.4, 2.5), rng.uniform(1.0, 2.6)])
        v = street.lateral(side * (road_half + sidewalk + rng.uniform(1, 8)))
        box = np.array([rng.uniform(-reach, reach), v, 0, *size, rng.normal(0, 0.1)])
        if clutter.layout.free(box, 0.3):
            clutter.boxes.append((box, rng.uniform(0.6, 1.6)))
            clutter.layout.add(box)


def _car_slot(rng, street: _Street, size: np.ndarray, max_center: float):
    """One try at a car's place: (u, v road frame, yaw) in a lane, along a curb, in a lot, on
    the cross street or anywhere off the road."""
    slot = rng.random()
    side = rng.choice([-1, 1])
    # nearer cars more often than farther ones (real drives: a third of the cars in view are
    # beyond 40 m), without a hole under the sensor
    u = rng.choice([-1, 1]) * max_center * rng.random() ** NEAR_BIAS
    if slot < 0.35:  # driving in a lane (right-hand traffic)
        lane_index = int(rng.integers(0, street.lanes_per_side))
        v = side * (lane_index + 0.5) * street.lane + rng.normal(0, 0.25)
        yaw = (0.0 if side < 0 else np.pi) + rng.normal(0, 0.03)
    elif slot < 0.75:  # parked along a curb
        v = side * (street.road_half - size[1] / 2 - rng.uniform(0.1, 0.4))
        yaw = rng.choice([0.0, np.pi]) + rng.normal(0, 0.04)
    elif slot < 0.9:  # rows in a lot beside the road, perpendicular
        v = side * (street.road_half + street.sidewalk + size[0] / 2 + rng.uniform(0.5, 6.0))
        yaw = rng.choice([np.pi / 2, -np.pi / 2]) + rng.normal(0, 0.06)
    elif street.cross:  # on the cross street
        u = street.cross_u + rng.uniform(-0.6, 0.6) * street.cross_half
        v = rng.uniform(-max_center, max_center)
        yaw = rng.choice([np.pi / 2, -np.pi / 2]) + rng.normal(0, 0.04)
    else:  # anywhere off the road at a random angle
        v = side * (street.road_half + street.sidewalk + rng.uniform(1.0, 30.0))
        yaw = rng.uniform(-np.pi, np.pi)
    return u, street.lateral(v), yaw


def _place_cars(rng, street, clutter, sensor, cars) -> list[np.ndarray]:
    """2-13 cars (ego road frame boxes) that overlap nothing; up to 30 tries each."""
    count = int(rng.integers(MIN_CARS, MAX_CARS + 1))
    sizes = sample_car_sizes(
        rng, count, np.array(cars.car_mean_lwh_m), np.array(cars.car_std_lwh_m)
    )
    placed: list[np.ndarray] = []
    max_center = min(MAX_RANGE_M, sensor.max_range_m + 5.0)
    for size in sizes:
        for _attempt in range(30):
            u, v, yaw = _car_slot(rng, street, size, max_center)
            if not MIN_RANGE_M <= np.hypot(u, v) <= max_center:
                continue
            box = np.array([u, v, 0.0, *size, yaw])
            if clutter.layout.free(box, 0.25):
                clutter.layout.add(box)
                placed.append(box)
                break
    return placed


def _to_sensor(boxes: np.ndarray, heading: float) -> np.ndarray:
    """Ego road frame boxes -> sensor frame (turned by the road heading)."""
    boxes = np.array(boxes, np.float64).reshape(-1, 7)
    boxes[:, :2] = rotate_xy(boxes[:, :2], heading)
    boxes[:, 6] = wrap_angle(boxes[:, 6] + heading)
    return boxes


def _clutter_mesh(clutter: _Clutter, ground: Ground, heading: float):
    """All clutter as one mesh in the sensor frame, standing on the ground: vertices (V, 3),
    faces (F, 3) int32, face reflectance (F,)."""
    clutter_v, clutter_f, clutter_r = [], [], []
    offset = 0
    for box, reflect in clutter.boxes:
        box = _to_sensor(box, heading)[0]
        sink = 0.5 if box[5] > 1.0 else 0.03  # buried a little so slopes leave no gap
        base = ground.height(box[:2]) - sink
        box[5] += sink
        box[2] = base + box[5] / 2
        vertices, faces = _box_mesh(box)
        clutter_v.append(vertices)
        clutter_f.append(faces + offset)
        clutter_r.append(np.full(len(faces), reflect))
        offset += len(vertices)
    for vertices, faces, reflect in clutter.meshes:
        vertices = vertices.copy()
        vertices[:, :2] = rotate_xy(vertices[:, :2], heading)
        vertices[:, 2] += ground.height(vertices[:, :2].mean(axis=0))
        clutter_v.append(vertices)
        clutter_f.append(faces + offset)
        clutter_r.append(np.full(len(faces), reflect))
        offset += len(vertices)
    return (
        np.concatenate(clutter_v),
        np.concatenate(clutter_f).astype(np.int32),
        np.concatenate(clutter_r),
    )


def generate_scene(
    rng: np.random.Generator, sensor: SensorProfile, cars: SensorProfile
) -> SynthScene:
    """Lay out one street scene (see module docstring); every draw comes from `rng`, in order:
    ground and road, sidewalks, walls, fences and hedges, street ends, poles and trees, bushes and containers, cars, car models."""
    ground, street = _ground_and_street(rng, sensor)
    clutter = _Clutter()
    _add_sidewalks(rng, street, clutter)
    _add_walls(rng, street, clutter)
    _add_fences_and_hedges(rng, street, clutter)
    _add_street_ends(rng, street, clutter)
    _add_poles_and_trees(rng, street, clutter)
    _add_bushes_and_containers(rng, street, clutter)
    placed = _place_cars(rng, street, clutter, sensor, cars)
    car_boxes = _to_sensor(np.array(placed).reshape(-1, 7), street.heading)
    car_boxes[:, 2] = ground.height(car_boxes[:, :2]) + car_boxes[:, 5] / 2  # on the ground
    vertices, faces, reflectance = _clutter_mesh(clutter, ground, street.heading)
    lanes = street.lanes_per_side
    lane_lines = np.arange(-lanes + 1, lanes) * street.lane - street.ego_v  # ego-lateral
    return SynthScene(
        ground=ground,
        cars=car_boxes,
        car_models=rng.integers(0, POOL_SIZE, len(car_boxes)),
        # paint from near-black to white: real car returns are mostly dark, a few bright
        car_reflectance=np.exp(rng.uniform(np.log(0.15), np.log(3.0), len(car_boxes))),
        clutter_vertices=vertices,
        clutter_faces=faces,
        face_reflectance=reflectance,
        road_heading=street.heading,
        lane_lines=lane_lines,
    )
