"""Ray casting against triangle meshes with Embree (embreex, used directly): BVHs, hits, placed models.

A `Scene` holds one or more triangle meshes in one Embree BVH (geometry id = position in the list);
`MeshBVH` is a scene of one mesh, cached by content (`get_bvh`). To place a model in a box the
**rays** are moved into the model frame (o' = A^-1 (o - t), d' = A^-1 d, d' not renormalized so the
ray parameter t stays valid) instead of transforming or rebuilding the mesh: one BVH per model.

embreex traps guarded here: inputs are made float32 C-contiguous; origin/direction row counts are
checked (embreex reads a short array out of bounds); every scene is committed once at construction,
so no geometry can be added after the first trace (embreex would silently ignore it); distances come
back as float32, so hit points are computed in float64 from origins moved close to the target.
Embree's robust mode is on (without it 12-21% of rays aimed at vertices miss). embreex traces on one
thread but releases the GIL, so large batches are chunked over a thread pool.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from dali_cli.geometry import rotation_z
from dali_cli.runtime.cores import available_cores

_MIN_RAYS_PER_THREAD = 16_384
_CACHE_SIZE = 512
_FAR = np.float32(1e30)  # "no limit" for Embree's tfar


class RayHits:
    """First hits of N rays.

    hit: `(N,)` bool. distance: `(N,)` float64 ray parameter t of the hit (metres for unit
    directions), inf on a miss. points: `(N, 3)` float32 hit points o + t d, NaN on a miss.
    geometry_id / primitive_id: `(N,)` int32 mesh index in the scene / triangle index in that
    mesh, -1 on a miss. normals: `(N, 3)` float32 unit geometric normals of the hit triangles in
    the ray frame (sign: as the triangle winds), zero on a miss; computed on first access.
    """

    def __init__(
        self,
        hit: np.ndarray,
        distance: np.ndarray,
        points: np.ndarray,
        geometry_id: np.ndarray,
        primitive_id: np.ndarray,
        normals: np.ndarray | None = None,
        raw_normals: np.ndarray | None = None,
        normal_transform: np.ndarray | None = None,
    ):
        self.hit = hit
        self.distance = distance
        self.points = points
        self.geometry_id = geometry_id
        self.primitive_id = primitive_id
        self._normals = normals
        self._raw_normals = raw_normals  # (N, 3) unnormalized, any value on a miss
        self._normal_transform = normal_transform  # (3, 3) applied to raw normals, or None

    @property
    def normals(self) -> np.ndarray:
        if self._normals is None:
            raw = np.asarray(self._raw_normals, np.float32)
            if self._normal_transform is not None:
                raw = _apply(self._normal_transform, raw.astype(np.float64)).astype(np.float32)
            squared = np.einsum("ij,ij->i", raw, raw)
            scale = np.zeros(len(raw), np.float32)
            good = self.hit & (squared > 0)
            scale[good] = 1.0 / np.sqrt(squared[good])
            self._normals = raw * scale[:, None]
        return self._normals

    def __len__(self) -> int:
        return len(self.hit)

    @classmethod
    def misses(cls, count: int) -> RayHits:
        return cls(
            hit=np.zeros(count, bool),
            distance=np.full(count, np.inf),
            points=np.full((count, 3), np.nan, np.float32),
            geometry_id=np.full(count, -1, np.int32),
            primitive_id=np.full(count, -1, np.int32),
            normals=np.zeros((count, 3), np.float32),
        )

    def cosine_incidence(self, directions: np.ndarray) -> np.ndarray:
        """|cos| of the angle between each ray and the hit surface normal, `(N,)` float32 (0 on miss)."""
        directions = np.asarray(directions, dtype=np.float32)
        lengths = np.sqrt(np.einsum("ij,ij->i", directions, directions))
        cosine = np.abs(np.einsum("ij,ij->i", self.normals, directions))
        return np.where(lengths > 0, cosine / np.maximum(lengths, 1e-30), 0.0).astype(np.float32)


def _as_mesh(vertices: np.ndarray, faces: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    faces_in = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise ValueError(f"{name}: vertices must be a non-empty (V, 3) array, got {vertices.shape}")
    if faces_in.ndim != 2 or faces_in.shape[1] != 3 or len(faces_in) == 0:
        raise ValueError(f"{name}: faces must be a non-empty (F, 3) array, got {faces_in.shape}")
    if not np.issubdtype(faces_in.dtype, np.integer):
        raise ValueError(f"{name}: faces must be integers, got {faces_in.dtype}")
    if faces_in.min() < 0 or faces_in.max() >= len(vertices):
        raise ValueError(f"{name}: face indices out of range [0, {len(vertices)})")
    if not np.isfinite(vertices).all():
        raise ValueError(f"{name}: vertices contain NaN/inf")
    return vertices, np.ascontiguousarray(faces_in, dtype=np.int32)


class Scene:
    """An immutable Embree BVH over several triangle meshes; geometry id = index in `meshes`.

    meshes: sequence of (vertices `(V_i, 3)` float, faces `(F_i, 3)` int). The scene is committed
    at construction; it is safe to trace from several threads at once.
    """

    def __init__(self, meshes: Sequence[tuple[np.ndarray, np.ndarray]]):
        from embreex import mesh_construction, rtcore_scene

        if len(meshes) == 0:
            raise ValueError("a scene needs at least one mesh")
        self.vertices: list[np.ndarray] = []
        self.faces: list[np.ndarray] = []
        self._scene = rtcore_scene.EmbreeScene(robust=True)
        for index, (vertices, faces) in enumerate(meshes):
            vertices, faces = _as_mesh(vertices, faces, f"mesh {index}")
            mesh_construction.TriangleMesh(self._scene, vertices, faces)
            self.vertices.append(vertices)
            self.faces.append(faces)
        # commit now (embreex commits on the first run()); later geometry would be ignored anyway
        probe = np.zeros((1, 3), np.float32)
        self._scene.run(probe, np.array([[0, 0, 1]], np.float32), output=1)
        self.bounds = np.stack(
            [
                np.min([v.min(axis=0) for v in self.vertices], axis=0),
                np.max([v.max(axis=0) for v in self.vertices], axis=0),
            ]
        ).astype(np.float64)  # (2, 3) min, max corner
        # bounding sphere (center (3,), radius) with 1% slack, for moving ray origins close
        self.sphere = (
            self.bounds.mean(axis=0),
            0.5 * float(np.linalg.norm(self.bounds[1] - self.bounds[0])) * 1.01 + 1e-6,
        )

    @classmethod
    def from_meshes(cls, meshes: Sequence[tuple[np.ndarray, np.ndarray]]) -> Scene:
        return cls(meshes)

    @property
    def num_geometries(self) -> int:
        return len(self.faces)

    @property
    def num_triangles(self) -> int:
        return int(sum(len(f) for f in self.faces))

    def cast(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        max_distance: float | np.ndarray | None = None,
        threads: int | None = None,
    ) -> RayHits:
        return cast(self, origins, directions, max_distance=max_distance, threads=threads)

    def _trace(self, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray) -> dict:
        """Raw embreex call on float32 C-contiguous arrays of equal length; tfar is overwritten."""
        return self._scene.run(origins, directions, dists=tfar, output=1)


class MeshBVH(Scene):
    """The BVH of one triangle mesh (geometry id 0). Build with `from_mesh` or `get_bvh` (cached)."""

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, faces: np.ndarray) -> MeshBVH:
        return cls([(vertices, faces)])


_cache: OrderedDict[str, MeshBVH] = OrderedDict()
_cache_lock = threading.Lock()


def mesh_key(vertices: np.ndarray, faces: np.ndarray) -> str:
    """Content hash of a mesh (float32 vertices, int32 faces)."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    digest = hashlib.blake2b(digest_size=16)
    digest.update(np.asarray(vertices.shape + faces.shape, np.int64).tobytes())
    digest.update(vertices.tobytes())
    digest.update(faces.tobytes())
    return digest.hexdigest()


def get_bvh(vertices: np.ndarray, faces: np.ndarray) -> MeshBVH:
    """The BVH of a mesh, built once per process and cached by content (LRU, 512 meshes)."""
    key = mesh_key(vertices, faces)
    with _cache_lock:
        bvh = _cache.get(key)
        if bvh is not None:
            _cache.move_to_end(key)
            return bvh
    bvh = MeshBVH.from_mesh(vertices, faces)
    with _cache_lock:
        _cache[key] = bvh
        while len(_cache) > _CACHE_SIZE:
            _cache.popitem(last=False)
    return bvh


_pools: dict[int, ThreadPoolExecutor] = {}
_pools_lock = threading.Lock()


def _pool(threads: int) -> ThreadPoolExecutor:
    with _pools_lock:
        if threads not in _pools:
            _pools[threads] = ThreadPoolExecutor(threads, thread_name_prefix="dali-raycast")
        return _pools[threads]


def _trace_chunked(
    scene: Scene,
    origins: np.ndarray,
    directions: np.ndarray,
    tfar: np.ndarray,
    threads: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Trace float32 rays; returns tfar (N,) float32, geomID, primID (N,) int32, Ng (N, 3) float32."""
    count = len(origins)
    threads = available_cores() if threads is None else max(1, int(threads))
    chunks = min(threads, max(1, count // _MIN_RAYS_PER_THREAD))
    if chunks == 1:
        out = scene._trace(origins, directions, tfar)
        return out["tfar"], out["geomID"], out["primID"], out["Ng"]
    bounds = np.linspace(0, count, chunks + 1).astype(np.int64)

    def run(index: int) -> dict:
        a, b = bounds[index], bounds[index + 1]
        return scene._trace(origins[a:b], directions[a:b], tfar[a:b].copy())

    parts = list(_pool(threads).map(run, range(chunks)))
    return (
        np.concatenate([p["tfar"] for p in parts]),
        np.concatenate([p["geomID"] for p in parts]),
        np.concatenate([p["primID"] for p in parts]),
        np.concatenate([p["Ng"] for p in parts]),
    )


_zeros = np.zeros((0, 3), np.float32)


def _zero_origins(count: int) -> np.ndarray:
    """A read-only `(count, 3)` float32 zero array (Embree never writes origins), reused."""
    global _zeros
    if len(_zeros) < count:
        _zeros = np.zeros((max(count, 2 * len(_zeros)), 3), np.float32)
        _zeros.flags.writeable = False
    return _zeros[:count]


def _apply(matrix: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """`matrix (3, 3) @ v` for each row of `vectors (N, 3)`. einsum, not `@`: a BLAS call with an
    inner size of 3 is slow and spawns threads that fight over a loaded CPU."""
    return np.einsum("kj,ij->ik", matrix, vectors)


def _checked_rays(origins, directions: np.ndarray) -> tuple[np.ndarray, bool]:
    """Check a ray batch: `directions` `(N, 3)`, `origins` one shared `(3,)` or `(N, 3)`, all
    finite (ValueError otherwise). Returns (origins as float64, whether the origin is shared)."""
    if directions.ndim != 2 or directions.shape[1] != 3:
        raise ValueError(f"directions must be (N, 3), got {directions.shape}")
    origins = np.asarray(origins, np.float64)
    shared = origins.shape == (3,)
    if not shared and origins.shape != directions.shape:
        raise ValueError(
            f"origins {origins.shape} and directions {directions.shape} differ in shape"
        )
    if not (np.isfinite(origins).all() and np.isfinite(directions).all()):
        raise ValueError("origins/directions contain NaN/inf")
    return origins, shared


def cast(
    bvh: Scene,
    origins: np.ndarray,
    directions: np.ndarray,
    max_distance: float | np.ndarray | None = None,
    threads: int | None = None,
) -> RayHits:
    """First hit of each ray in a scene.

    origins: `(N, 3)` or `(3,)` float; directions: `(N, 3)` float (need not be unit; distances are
    in units of |d|). max_distance: scalar or `(N,)` limit on t (hits beyond are misses).
    threads: worker threads for large batches (default: cores available).
    Float32 C-contiguous directions are passed to Embree without a copy; hit points are
    computed in float64 from the original origins and directions.
    """
    directions32 = np.ascontiguousarray(directions, dtype=np.float32)
    origins64, shared = _checked_rays(origins, directions32)
    count = len(directions32)
    if count == 0:
        return RayHits.misses(0)
    if shared and not origins64.any():
        origins32 = _zero_origins(count)
    elif shared:
        origins32 = np.empty((count, 3), np.float32)
        origins32[:] = origins64.astype(np.float32)
    else:
        origins32 = np.ascontiguousarray(origins64, dtype=np.float32)
    if max_distance is None:
        tfar = np.full(count, _FAR, np.float32)
    else:
        limit = np.broadcast_to(np.asarray(max_distance, np.float64), (count,))
        tfar = np.where(np.isfinite(limit), limit, _FAR).astype(np.float32)
    empty = tfar <= 0
    tfar[empty] = np.float32(1e-30)
    local, geometry, primitive, normals = _trace_chunked(
        bvh, origins32, directions32, tfar, threads
    )
    hit = (geometry >= 0) & ~empty
    distance = np.where(hit, local, np.inf).astype(np.float64)
    if shared and not origins64.any():
        # from the origin, float32 t * d is exact to float32 rounding of the point itself
        points = directions32 * np.where(hit, local, np.float32(np.nan))[:, None]
    else:
        step = np.where(hit, distance, np.nan)[:, None] * np.asarray(directions, np.float64)
        points = (step + origins64).astype(np.float32)
    return RayHits(
        hit=hit,
        distance=distance,
        points=points,
        geometry_id=np.where(hit, geometry, -1).astype(np.int32),
        primitive_id=np.where(hit, primitive, -1).astype(np.int32),
        raw_normals=normals,
    )


def box_affine(
    box: np.ndarray, model_lwh: np.ndarray | Sequence[float] = (1.0, 1.0, 1.0)
) -> np.ndarray:
    """`(4, 4)` model → sensor affine A that fits a model of extent `model_lwh` into `box` (7,).

    The model frame has l along +x, w along +y, up +z, centered at the origin; the scale is
    anisotropic (box l, w, h / model l, w, h), then yaw, then the box center.
    """
    box = np.asarray(box, np.float64).reshape(7)
    scale = box[3:6] / np.asarray(model_lwh, np.float64)
    affine = np.eye(4)
    affine[:3, :3] = rotation_z(box[6]) * scale[None, :]
    affine[:3, 3] = box[:3]
    return affine


def cast_transformed(
    bvh: Scene,
    origins: np.ndarray,
    directions: np.ndarray,
    affine: np.ndarray,
    max_distance: float | np.ndarray | None = None,
    threads: int | None = None,
) -> RayHits:
    """First hits of sensor-frame rays on a model placed by the `(4, 4)` affine A (model → sensor).

    Rays go into the model frame (o' = A^-1 (o - t), d' = A^-1 d, not renormalized, so t is the
    same in both frames); hits, distances and normals come back in the sensor frame. Origins are
    first moved along their ray to near the model's bounding sphere so float32 tracing keeps
    sub-micrometre precision far from the sensor.
    """
    affine = np.asarray(affine, np.float64)
    return _cast_model_frame(
        bvh,
        origins,
        directions,
        np.linalg.inv(affine[:3, :3]),
        affine[:3, 3],
        max_distance,
        threads,
    )


def _cast_model_frame(
    bvh: Scene,
    origins: np.ndarray,
    directions: np.ndarray,
    inverse: np.ndarray,
    translation: np.ndarray,
    max_distance: float | np.ndarray | None,
    threads: int | None,
) -> RayHits:
    """cast_transformed given A^-1 `(3, 3)` and t `(3,)`; a `(3,)` origin is transformed once."""
    directions = np.asarray(directions, np.float64)
    origins, shared = _checked_rays(origins, directions)
    count = len(directions)
    if count == 0:
        return RayHits.misses(0)
    # model frame; a shared origin is one vector
    model_origins = (
        inverse @ (origins - translation) if shared else _apply(inverse, origins - translation)
    )
    model_directions = _apply(inverse, directions)  # (N, 3)
    # start each ray just before the model's bounding sphere (t is frame independent)
    center, radius = bvh.sphere
    squared = np.maximum(np.einsum("ij,ij->i", model_directions, model_directions), 1e-300)
    to_center = center - model_origins
    along = (
        model_directions @ to_center
        if shared
        else np.einsum("ij,ij->i", to_center, model_directions)
    )
    start = np.maximum(0.0, (along - radius * np.sqrt(squared)) / squared)  # (N,)
    moved = model_origins + start[:, None] * model_directions
    if max_distance is None:
        tfar = np.full(count, _FAR, np.float32)
    else:
        limit = np.broadcast_to(np.asarray(max_distance, np.float64), (count,))
        tfar = np.where(np.isfinite(limit), limit - start, _FAR).astype(np.float32)
    empty = tfar <= 0
    tfar[empty] = np.float32(1e-30)
    local, geometry, primitive, normals = _trace_chunked(
        bvh,
        np.ascontiguousarray(moved, dtype=np.float32),
        np.ascontiguousarray(model_directions, dtype=np.float32),
        tfar,
        threads,
    )
    hit = (geometry >= 0) & ~empty
    distance = np.where(hit, start + local, np.inf)
    points = origins + np.where(hit, distance, np.nan)[:, None] * directions
    return RayHits(
        hit=hit,
        distance=distance,
        points=points.astype(np.float32),
        geometry_id=np.where(hit, geometry, -1).astype(np.int32),
        primitive_id=np.where(hit, primitive, -1).astype(np.int32),
        raw_normals=normals,
        normal_transform=inverse.T,  # normals are covectors: n_sensor ∝ A^-T n_model
    )


def cast_into_box(
    bvh: Scene,
    origins: np.ndarray,
    directions: np.ndarray,
    box: np.ndarray,
    model_lwh: np.ndarray | Sequence[float] = (1.0, 1.0, 1.0),
    max_distance: float | np.ndarray | None = None,
    threads: int | None = None,
) -> RayHits:
    """First hits on a model (extent `model_lwh`, centered, l along +x) scaled and placed in `box`.

    box: `(7,)` x, y, z, l, w, h, yaw (sensor frame). The model is scaled anisotropically to the
    box's l, w, h. Equivalent to tracing the transformed mesh, without rebuilding any BVH.
    """
    box = np.asarray(box, np.float64).reshape(7)
    scale = box[3:6] / np.asarray(model_lwh, np.float64)
    c, s = np.cos(box[6]), np.sin(box[6])
    # (R diag(scale))^-1 = diag(1 / scale) R^T
    inverse = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) / scale[:, None]
    return _cast_model_frame(bvh, origins, directions, inverse, box[:3], max_distance, threads)


def transform_vertices(vertices: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Apply a `(4, 4)` affine to `(V, 3)` vertices → `(V, 3)` float64 (reference for tests)."""
    affine = np.asarray(affine, np.float64)
    return _apply(affine[:3, :3], np.asarray(vertices, np.float64)) + affine[:3, 3]
