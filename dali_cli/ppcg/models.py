"""The models PPCG fits into boxes: one kind (CAD meshes or point models), selection and ray casting.

`ModelBank` is the PPCG view of a model library: native sizes for selection, and one `cast` that
returns first hits of sensor rays on a model fitted into a box, whatever the model kind. Mesh BVHs
are built lazily, once per model and process, and kept by model index (no per-call hashing).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dali_cli.ppcg.fitting import (
    box_affine_inverse,
    model_to_sensor,
    rays_to_model,
    select_cad_models,
    select_point_models,
    viewing_angle,
)
from dali_cli.ppcg.point_models import cast_point_model

KINDS = ("cad", "points")


@dataclass
class ModelBank:
    """Models of one kind in the unit-box frame (l along +x, up +z, centred at the origin).

    kind: "cad" or "points". model_ids: M names. lwh: `(M, 3)` native sizes (m).
    meshes: M (vertices `(V, 3)`, faces `(F, 3)`) for "cad"; for "points": points `(P, >=3)`
    all models' normalized points with offsets `(M + 1,)` (model k is points[offsets[k]:
    offsets[k + 1]]) and angles `(M,)` viewing angles (rad, see fitting.viewing_angle).
    """

    kind: str
    model_ids: list[str]
    lwh: np.ndarray
    meshes: list[tuple[np.ndarray, np.ndarray]] | None = None
    points: np.ndarray | None = None
    offsets: np.ndarray | None = None
    angles: np.ndarray | None = None
    angle_tolerance_rad: float = np.radians(5.0)
    _bvhs: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown model kind '{self.kind}' (known: {', '.join(KINDS)})")
        self.lwh = np.asarray(self.lwh, dtype=np.float64).reshape(-1, 3)
        count = len(self.model_ids)
        if count == 0:
            raise ValueError(f"no {self.kind} models")
        if len(self.lwh) != count:
            raise ValueError(f"{len(self.lwh)} sizes for {count} models")
        if self.kind == "cad" and (self.meshes is None or len(self.meshes) != count):
            raise ValueError("cad models need one mesh per model")
        if self.kind == "points":
            if self.points is None or self.offsets is None or len(self.offsets) != count + 1:
                raise ValueError("point models need points and offsets (M + 1,)")
            if self.angles is None or len(self.angles) != count:
                raise ValueError("point models need one viewing angle per model")
            self.angles = np.asarray(self.angles, dtype=np.float64)

    def __len__(self) -> int:
        return len(self.model_ids)

    @classmethod
    def from_library(cls, library, kind: str, source: str = "library") -> ModelBank:
        """The meshes ("cad") or point models ("points") of a library.ModelLibrary."""
        if kind == "cad":
            if not library.meshes:
                raise ValueError(f"{source}: the library has no meshes (use --models points?)")
            meshes = [(m.vertices, m.faces) for m in library.meshes]
            return cls("cad", library.mesh_ids, library.mesh_lwh, meshes=meshes)
        if kind == "points":
            models = library.point_models
            if len(models) == 0:
                raise ValueError(f"{source}: the library has no point models (use --models cad?)")
            return cls(
                "points",
                [str(m) for m in models.model_id],
                models.lwh,
                points=models.points,
                offsets=models.offsets,
                angles=models.view_angle_rad,
            )
        raise ValueError(f"unknown model kind '{kind}' (known: {', '.join(KINDS)})")

    def model_points(self, index: int) -> np.ndarray:
        """Normalized points `(P, 3)` of point model `index`."""
        return self.points[self.offsets[index] : self.offsets[index + 1], :3]

    def select(
        self, boxes: np.ndarray, top_k: int = 1, rngs: list[np.random.Generator] | None = None
    ) -> np.ndarray:
        """Model index for each box `(N, 7)` -> `(N,)` int64 (METHOD: PPCG selection)."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        if len(boxes) == 0:
            return np.zeros(0, dtype=np.int64)
        if self.kind == "cad":
            return select_cad_models(boxes[:, 3:6], self.lwh, top_k, rngs)
        return select_point_models(
            viewing_angle(boxes),
            boxes[:, 3:6],
            self.angles,
            self.lwh,
            self.angle_tolerance_rad,
            top_k,
            rngs,
        )

    def bvh(self, index: int):
        """The Embree BVH of mesh `index`, built on first use (raycast's content cache keeps it
        for other banks of the same process; this dict spares hashing the mesh on every call)."""
        bvh = self._bvhs.get(index)
        if bvh is None:
            from dali_cli.raycast import get_bvh

            vertices, faces = self.meshes[index]
            bvh = self._bvhs[index] = get_bvh(vertices, faces)
        return bvh

    def cast(
        self, index: int, box: np.ndarray, directions: np.ndarray, theta_rad: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """First hits of rays from the sensor origin on model `index` fitted into `box` `(7,)`.

        directions `(N, 3)` (any length); theta_rad: point-model angular threshold (unused for
        meshes). Returns hit `(N,)` bool and points `(N, 3)` float64 (NaN on a miss), sensor frame.
        """
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        if len(directions) == 0:
            return np.zeros(0, bool), np.zeros((0, 3))
        if self.kind == "cad":
            return _cast_mesh(self.bvh(index), box, directions)
        placed = model_to_sensor(self.model_points(index), box)
        hits = cast_point_model(np.zeros(3), directions, placed, theta_rad)
        return hits.hit, hits.points

    def cast_many(
        self,
        models: np.ndarray,
        boxes: np.ndarray,
        directions: np.ndarray,
        bounds: np.ndarray,
        theta_rad: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """`cast` for B boxes at once: rays bounds[b]:bounds[b + 1] of `directions` `(N, 3)` go
        to model models[b] in boxes[b]. bounds `(B + 1,)` from 0 to N. Same result as B `cast`
        calls; for meshes the ray set-up is vectorized over all boxes and only the Embree call
        runs per box. Returns hit `(N,)` bool and points `(N, 3)` float64 (NaN on a miss)."""
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        bounds = np.asarray(bounds, dtype=np.int64)
        if self.kind == "points":
            hit = np.zeros(len(directions), bool)
            points = np.full((len(directions), 3), np.nan)
            for b, (model, box) in enumerate(zip(models, boxes, strict=True)):
                segment = slice(bounds[b], bounds[b + 1])
                hit[segment], points[segment] = self.cast(
                    int(model), box, directions[segment], theta_rad
                )
            return hit, points
        box_of_ray = np.repeat(np.arange(len(boxes)), np.diff(bounds))  # (N,)
        inverse = np.stack([box_affine_inverse(box) for box in boxes])  # (B, 3, 3)
        origin = np.einsum("bij,bj->bi", inverse, -boxes[:, :3])  # (B, 3) sensor in model frames
        model_directions = np.einsum("nij,nj->ni", inverse[box_of_ray], directions)  # (N, 3)
        origins = origin[box_of_ray]  # (N, 3)
        squared = np.einsum("ij,ij->i", model_directions, model_directions)
        along = -np.einsum("ij,ij->i", model_directions, origins) / squared
        start = np.maximum(along - _UNIT_BOX_RADIUS / np.sqrt(squared), 0.0)  # (N,)
        origins32 = (origins + start[:, None] * model_directions).astype(np.float32)
        directions32 = model_directions.astype(np.float32)
        far = np.full(len(directions), 1e30, dtype=np.float32)
        geometry = np.full(len(directions), -1, dtype=np.int32)
        for b, model in enumerate(models):  # one Embree call per box (its own BVH and pose)
            a, z = bounds[b], bounds[b + 1]
            if z > a:
                result = self.bvh(int(model))._trace(origins32[a:z], directions32[a:z], far[a:z])
                geometry[a:z] = result["geomID"]
                far[a:z] = result["tfar"]
        hit = geometry >= 0
        distance = start + far.astype(np.float64)
        return hit, np.where(hit[:, None], distance[:, None] * directions, np.nan)


# the model lies in the unit box, inside this radius around the origin (with a little slack)
_UNIT_BOX_RADIUS = 0.5 * np.sqrt(3.0) * 1.01


def _cast_mesh(bvh, box: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hits of rays from the sensor origin on a unit-box mesh fitted into `box`.

    The lean path of raycast.cast_into_box for one shared origin (about 6x less overhead per call,
    which matters at ~15 boxes per frame): rays go into the model frame, start just before the
    model's bounding sphere (float32 precision near the model), and hits are rebuilt in float64
    along the given sensor-frame directions, so they lie exactly on their rays.
    directions `(N, 3)` float64 -> hit `(N,)` bool, points `(N, 3)` float64 (NaN on a miss).
    """
    origin, model_directions = rays_to_model(np.zeros(3), directions, box)  # (3,), (N, 3)
    squared = np.einsum("ij,ij->i", model_directions, model_directions)  # (N,)
    along = (model_directions @ -origin) / squared  # ray parameter closest to the model centre
    start = np.maximum(along - _UNIT_BOX_RADIUS / np.sqrt(squared), 0.0)  # (N,)
    origins = origin + start[:, None] * model_directions
    far = np.full(len(directions), 1e30, dtype=np.float32)
    result = bvh._trace(  # raycast's raw embreex call: float32 C-contiguous, tfar overwritten
        np.ascontiguousarray(origins, dtype=np.float32),
        np.ascontiguousarray(model_directions, dtype=np.float32),
        far,
    )
    hit = result["geomID"] >= 0
    distance = start + result["tfar"].astype(np.float64)
    return hit, np.where(hit[:, None], distance[:, None] * directions, np.nan)
