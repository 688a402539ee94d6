"""The synthetic world's cars: a fixed pool of procedural car models (seeds disjoint from `dali
library build --procedural`) and car sizes drawn around a profile's mean with its spread."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from dali_cli.geometry import shrink_boxes
from dali_cli.library import normalize_mesh
from dali_cli.procedural import generate_car_mesh

POOL_SALT = 0x5EED_CA25  # the synthetic car pool's seed space (library cars use [seed, i])
POOL_SIZE = 64
POOL_LOD = 6000
SIZE_CORRELATION = 0.6  # cars that are long tend to be wide and tall too
# A labelled box holds its car with room to spare, as annotators draw them: the car's body ends
# this far inside each end face, each side face and the top face (metres).
LABEL_SLACK_M = np.array([0.035, 0.02, 0.035])


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


def sample_car_sizes(
    rng: np.random.Generator, count: int, mean: np.ndarray, std: np.ndarray
) -> np.ndarray:
    """`(count, 3)` l, w, h around `mean` with spread `std`, correlated, clipped at 2.5 sigma."""
    common = rng.standard_normal((count, 1))
    own = rng.standard_normal((count, 3))
    z = SIZE_CORRELATION * common + np.sqrt(1 - SIZE_CORRELATION**2) * own
    return np.asarray(mean) + np.asarray(std) * np.clip(z, -2.5, 2.5)


def body_box(box: np.ndarray) -> np.ndarray:
    """The box `(7,)` a car's mesh fills inside its label `box` `(7,)` (LABEL_SLACK_M; same bottom)."""
    return shrink_boxes(box, LABEL_SLACK_M)[0]
