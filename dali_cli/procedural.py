"""A seeded procedural car generator: lofted body with greenhouse, rounded edges, wheels, surface detail.

The body is a loft of rounded-rectangle (superellipse) cross-sections along the car's length; each
section spans the bottom and top silhouettes of the kind's side profile, keeps the body width up
to the beltline and narrows above it (the greenhouse), and shrinks in plan near the bumpers. Four
cylindrical wheels sit inside the body width on the ground. A smooth random displacement of a few
millimetres gives every model its own surface detail. Output is in metres, x forward, y left,
z up, wheels on z = 0; `library.CarModel` normalizes it to the unit box.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

KINDS = ("sedan", "hatchback", "suv", "van", "pickup")
KIND_WEIGHTS = (0.40, 0.20, 0.25, 0.08, 0.07)
MIN_LOD, MAX_LOD = 1_000, 200_000

# Side silhouettes: (fraction of length from the front bumper, fraction of height) key points of
# the roof line; jittered per model. The beltline is where the greenhouse (windows) starts.
_TOP_PROFILES = {
    "sedan": (
        (0.0, 0.52),
        (0.03, 0.62),
        (0.28, 0.68),
        (0.43, 1.0),
        (0.70, 1.0),
        (0.84, 0.72),
        (0.98, 0.70),
        (1.0, 0.58),
    ),
    "hatchback": (
        (0.0, 0.50),
        (0.03, 0.60),
        (0.25, 0.66),
        (0.43, 1.0),
        (0.86, 0.97),
        (0.97, 0.72),
        (1.0, 0.55),
    ),
    "suv": (
        (0.0, 0.55),
        (0.03, 0.66),
        (0.23, 0.71),
        (0.37, 1.0),
        (0.94, 0.99),
        (0.99, 0.80),
        (1.0, 0.60),
    ),
    "van": ((0.0, 0.45), (0.03, 0.55), (0.11, 0.60), (0.28, 1.0), (0.97, 0.99), (1.0, 0.70)),
    "pickup": (
        (0.0, 0.52),
        (0.03, 0.60),
        (0.26, 0.66),
        (0.37, 1.0),
        (0.55, 1.0),
        (0.57, 0.69),
        (0.98, 0.67),
        (1.0, 0.58),
    ),
}
# nominal (length, width, height) in metres and relative spread of each kind
_NOMINAL = {
    "sedan": ((4.65, 1.80, 1.45), (0.06, 0.03, 0.03)),
    "hatchback": ((4.10, 1.75, 1.50), (0.06, 0.03, 0.04)),
    "suv": ((4.75, 1.90, 1.72), (0.06, 0.03, 0.04)),
    "van": ((5.05, 1.95, 1.98), (0.05, 0.03, 0.04)),
    "pickup": ((5.40, 1.95, 1.82), (0.06, 0.03, 0.04)),
}
# Real car ends bulge: the bumper's middle leads, its corners, the bonnet and the bottom trail.
# Ranges of the recess at the corners in plan and at the top/bottom in profile (metres), over a
# blend length that fades it out along the body.
END_BOW_M = (0.12, 0.28)
END_BOW_VERTICAL_M = (0.06, 0.16)
END_BOW_REACH_M = 0.9
_BELTLINE = {"sedan": 0.66, "hatchback": 0.64, "suv": 0.68, "van": 0.58, "pickup": 0.66}


@dataclass(frozen=True)
class CarShape:
    """The random draws behind one procedural car (metres)."""

    kind: str
    length: float
    width: float
    height: float
    clearance: float
    wheel_radius: float
    wheel_width: float
    wheelbase: float
    beltline: float  # height of the beltline
    roof_taper: float  # roof half-width / body half-width
    end_radius: float  # plan-view rounding radius at the bumpers
    end_bow: float  # how far the bumpers' corners sit behind their middle, in plan (m)
    end_bow_vertical: float  # how far the ends' top and bottom sit behind their middle (m)
    top_profile: np.ndarray  # (K, 2) x fraction from the front, z fraction of height
    detail_amplitude: float


def sample_shape(rng: np.random.Generator, kind: str | None = None) -> CarShape:
    """Draw the proportions of one car of `kind` (random kind by KIND_WEIGHTS when None)."""
    if kind is None:
        kind = str(rng.choice(KINDS, p=KIND_WEIGHTS))
    if kind not in KINDS:
        raise ValueError(f"unknown car kind '{kind}' (known: {', '.join(KINDS)})")
    nominal, spread = _NOMINAL[kind]
    length, width, height = np.asarray(nominal) * (
        1.0 + np.asarray(spread) * rng.standard_normal(3)
    )
    profile = np.array(_TOP_PROFILES[kind], dtype=np.float64)
    inner = slice(1, -1)
    profile[inner, 0] += rng.normal(0.0, 0.012, len(profile) - 2)
    profile[inner, 1] += rng.normal(0.0, 0.02, len(profile) - 2) * (profile[inner, 1] < 0.99)
    profile[:, 0] = np.maximum.accumulate(np.clip(profile[:, 0], 0.0, 1.0))
    wheel_radius = float(np.clip(0.31 * np.sqrt(height / 1.45) + rng.normal(0, 0.012), 0.27, 0.42))
    overhang = rng.uniform(0.17, 0.23)
    return CarShape(
        kind=kind,
        length=float(length),
        width=float(width),
        height=float(height),
        clearance=float(rng.uniform(0.13, 0.20) * (1.25 if kind in ("suv", "pickup") else 1.0)),
        wheel_radius=wheel_radius,
        wheel_width=float(rng.uniform(0.19, 0.26)),
        wheelbase=float(length * (1.0 - 2.0 * overhang)),
        beltline=float(height * (_BELTLINE[kind] + rng.normal(0.0, 0.015))),
        roof_taper=float(rng.uniform(0.78, 0.90)),
        end_radius=float(rng.uniform(0.25, 0.45)),
        end_bow=float(rng.uniform(END_BOW_M[0], END_BOW_M[1])),
        end_bow_vertical=float(rng.uniform(END_BOW_VERTICAL_M[0], END_BOW_VERTICAL_M[1])),
        top_profile=profile,
        detail_amplitude=float(rng.uniform(0.004, 0.012)),
    )


def _smooth(values: np.ndarray, positions: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of samples `(n,)` at sorted `positions` `(n,)` (non-uniform spacing)."""
    weights = np.exp(-0.5 * ((positions[:, None] - positions[None, :]) / sigma) ** 2)  # (n, n)
    return (weights @ values) / weights.sum(axis=1)


def _grid_triangles(rows: int, columns: int, wrap: bool) -> np.ndarray:
    """Two triangles per quad of a rows x columns vertex grid (columns wrap around when `wrap`)."""
    r, c = np.meshgrid(
        np.arange(rows - 1), np.arange(columns if wrap else columns - 1), indexing="ij"
    )
    c_next = (c + 1) % columns
    a, b = r * columns + c, r * columns + c_next
    d, e = (r + 1) * columns + c, (r + 1) * columns + c_next
    return np.concatenate(
        [np.stack([a, d, e], -1).reshape(-1, 3), np.stack([a, e, b], -1).reshape(-1, 3)]
    )


def _body(shape: CarShape, stations: int, around: int, rng: np.random.Generator):
    """Lofted body: vertices `(stations * around + 2, 3)`, faces `(2 * stations * around, 3)`."""
    L, H = shape.length, shape.height
    linear = np.linspace(0.0, 1.0, stations)
    fraction = 0.5 * linear + 0.5 * (0.5 - 0.5 * np.cos(np.pi * linear))  # denser at the bumpers
    x = (0.5 - fraction) * L  # front bumper at +L/2
    top = np.interp(fraction, shape.top_profile[:, 0], shape.top_profile[:, 1]) * H
    top = _smooth(top, fraction * L, 0.06)
    bumper = 0.30 * H
    bottom = np.interp(
        fraction, [0.0, 0.07, 0.93, 1.0], [bumper, shape.clearance, shape.clearance, bumper]
    )
    bottom = _smooth(bottom, fraction * L, 0.05)
    # wheel arches: the sill rises over each axle so the wheels show from the side
    arch = shape.wheel_radius + 0.05
    for axle in (0.5 * shape.wheelbase, -0.5 * shape.wheelbase):
        rise = shape.wheel_radius + 0.92 * np.sqrt(np.maximum(arch**2 - (x - axle) ** 2, 0.0))
        bottom = np.where(np.abs(x - axle) < arch, np.maximum(bottom, rise), bottom)
    bottom = np.minimum(bottom, top - 0.15)
    # plan view: round the corners near the bumpers
    end_distance = np.minimum(fraction, 1.0 - fraction) * L
    rounding = np.sqrt(1.0 - (1.0 - np.clip(end_distance / shape.end_radius, 0.0, 1.0)) ** 2)
    half_width = 0.5 * shape.width * (0.72 + 0.28 * rounding)  # (S,)

    angle = (
        np.linspace(0.0, 2.0 * np.pi, around, endpoint=False) - 0.5 * np.pi
    )  # start at the bottom
    exponent = 2.0 / 5.0  # superellipse n = 5: a rounded rectangle
    u = np.sign(np.cos(angle)) * np.abs(np.cos(angle)) ** exponent  # (A,) -1..1 across
    v = np.sign(np.sin(angle)) * np.abs(np.sin(angle)) ** exponent  # (A,) -1..1 up
    z = bottom[:, None] + 0.5 * (v[None, :] + 1.0) * (top - bottom)[:, None]  # (S, A)
    greenhouse = np.clip((z - shape.beltline) / max(H - shape.beltline, 1e-3), 0.0, 1.0)
    width_at_z = half_width[:, None] * (1.0 - (1.0 - shape.roof_taper) * greenhouse)  # (S, A)
    y = u[None, :] * width_at_z

    # smooth per-model surface detail along the outward section direction
    radial = np.stack([y / (0.5 * shape.width), (z - 0.5 * H) / (0.5 * H)], -1)  # (S, A, 2)
    radial /= np.maximum(np.linalg.norm(radial, axis=-1, keepdims=True), 1e-9)
    bumps = np.zeros_like(z)
    for _ in range(4):  # a few random waves over (length, angle)
        kx, ka = rng.uniform(2.0, 9.0), rng.integers(2, 9)
        phase = rng.uniform(0.0, 2.0 * np.pi, 2)
        bumps += np.sin(kx * x[:, None] / L * 2 * np.pi + phase[0]) * np.sin(
            ka * angle[None, :] + phase[1]
        )
    displacement = shape.detail_amplitude * bumps / 2.0
    y = y + displacement * radial[..., 0]
    z = z + displacement * radial[..., 1]

    # ends bulge: recess each end section's vertices by their lateral and vertical offset
    span = np.maximum(top - bottom, 1e-3)[:, None]  # (S, 1)
    lateral = y / (0.5 * shape.width)  # (S, A) about -1..1
    vertical = 2.0 * (z - bottom[:, None]) / span - 1.0  # (S, A) -1..1
    blend = np.clip(1.0 - end_distance / END_BOW_REACH_M, 0.0, 1.0)[:, None]  # (S, 1)
    recess = blend * (shape.end_bow * lateral**2 + shape.end_bow_vertical * vertical**2)
    x_grid = x[:, None] - np.sign(x)[:, None] * recess  # (S, A)

    grid = np.stack([x_grid, y, z], -1).reshape(-1, 3)  # (S*A, 3)
    faces = _grid_triangles(stations, around, wrap=True)
    # caps: fans to the centroid of the first and last section
    front_center = grid[:around].mean(axis=0)
    rear_center = grid[-around:].mean(axis=0)
    front_center[0], rear_center[0] = x[0], x[-1]  # the ends' middles lead
    ring = np.arange(around)
    ring_next = (ring + 1) % around
    front_index, rear_index = len(grid), len(grid) + 1
    front_cap = np.stack([np.full(around, front_index), ring_next, ring], -1)
    rear_start = (stations - 1) * around
    rear_cap = np.stack(
        [np.full(around, rear_index), rear_start + ring, rear_start + ring_next], -1
    )
    vertices = np.concatenate([grid, front_center[None], rear_center[None]])
    return vertices, np.concatenate([faces, front_cap, rear_cap])


def _wheel(center: np.ndarray, radius: float, width: float, sections: int):
    """A closed cylinder along y: vertices `(2 * sections + 2, 3)`, faces `(4 * sections, 3)`."""
    angle = np.linspace(0.0, 2.0 * np.pi, sections, endpoint=False)
    ring = np.stack([radius * np.cos(angle), np.zeros(sections), radius * np.sin(angle)], -1)
    side = np.array([0.0, 0.5 * width, 0.0])
    vertices = np.concatenate([ring - side, ring + side, [-side, side]]) + center
    faces = _grid_triangles(2, sections, wrap=True)
    k = np.arange(sections)
    k_next = (k + 1) % sections
    caps = np.concatenate(
        [
            np.stack([np.full(sections, 2 * sections), k_next, k], -1),
            np.stack([np.full(sections, 2 * sections + 1), sections + k, sections + k_next], -1),
        ]
    )
    return vertices, np.concatenate([faces, caps])


def _resolution(lod: int) -> tuple[int, int, int]:
    """(stations, points around a section, wheel sections) for about `lod` triangles."""
    wheel_sections = int(np.clip(lod // 250, 16, 96))
    body = max(lod - 16 * wheel_sections, 500)
    around = int(max(12, round(np.sqrt(body / 5.0))))
    stations = int(max(8, round(body / (2.0 * around)) - 1))
    return stations, around, wheel_sections


def generate_car_mesh(
    seed: int | Sequence[int], kind: str | None = None, lod: int = 8000
) -> tuple[np.ndarray, np.ndarray, CarShape]:
    """A procedural car in metres: vertices `(V, 3)` float64, faces `(F, 3)` int32, its CarShape.

    seed: int or int sequence (np.random.default_rng). kind: one of KINDS or None (random).
    lod: approximate triangle count (documented range 5,000-70,000; 1,000-200,000 accepted).
    Deterministic for a given (seed, kind, lod). Wheels touch z = 0; x forward, y left, z up.
    """
    if not MIN_LOD <= int(lod) <= MAX_LOD:
        raise ValueError(f"lod must be in [{MIN_LOD}, {MAX_LOD}] triangles, got {lod}")
    rng = np.random.default_rng(seed)
    shape = sample_shape(rng, kind)
    stations, around, wheel_sections = _resolution(int(lod))
    parts = [_body(shape, stations, around, rng)]
    axle_x = 0.5 * shape.wheelbase
    axle_y = 0.5 * shape.width - 0.5 * shape.wheel_width - 0.02
    for wheel_x in (axle_x, -axle_x):
        for wheel_y in (axle_y, -axle_y):
            center = np.array([wheel_x, wheel_y, shape.wheel_radius])
            parts.append(_wheel(center, shape.wheel_radius, shape.wheel_width, wheel_sections))
    vertices, faces, offset = [], [], 0
    for part_vertices, part_faces in parts:
        vertices.append(part_vertices)
        faces.append(part_faces + offset)
        offset += len(part_vertices)
    vertices = np.concatenate(vertices)
    vertices[:, 2] -= vertices[:, 2].min()  # wheels on the ground
    return vertices, np.concatenate(faces).astype(np.int32), shape
