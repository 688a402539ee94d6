"""Ray casting front: Embree robust vs fast mode, float64 vs float32 ray set-up -> hit error vs rays/s.

The model is an exact box (a unit cube mesh subdivided into 768 triangles, so rays also cross
shared triangle edges), fitted into car-sized boxes 1-150 m from the sensor; the reference is the
float64 analytic intersection with the box's face planes. Rays go from the sensor to random
points on the box's triangle edges (half of them, where a non-watertight test lets rays slip
between triangles) and inside the box (the other half): every ray must hit.

Set-ups: "float64" is PPCG's (ModelBank.cast_many: rays moved into the model frame in float64 and
started at the model's bounding sphere, then handed to Embree in float32; hits rebuilt in float64
along the sensor-frame ray); "float32" does the same transform in float32 with rays starting at
the sensor, and returns float32 hit points.
"""

from __future__ import annotations

import time

import numpy as np

DEFAULT = {"robust": True, "setup": "float64"}


class _Scene:
    """One mesh in an Embree scene with a chosen robust flag (raycast.Scene is always robust)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, robust: bool):
        from embreex import mesh_construction, rtcore_scene

        self._scene = rtcore_scene.EmbreeScene(robust=robust)
        mesh_construction.TriangleMesh(
            self._scene,
            np.ascontiguousarray(vertices, np.float32),
            np.ascontiguousarray(faces, np.int32),
        )
        self._scene.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32), output=1)

    def _trace(self, origins, directions, tfar):
        return self._scene.run(origins, directions, dists=tfar, output=1)


def unit_box_mesh(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    mesh = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    for _ in range(subdivisions):
        mesh = mesh.subdivide()
    return np.asarray(mesh.vertices), np.asarray(mesh.faces), np.asarray(mesh.edges_unique)


def make_rays(count_boxes: int, rays_per_box: int, seed: int):
    """Boxes `(B, 7)` at 1-150 m, unit rays `(B * R, 3)` and bounds `(B + 1,)` (module doc)."""
    rng = np.random.default_rng(seed)
    vertices, _, edges = unit_box_mesh()
    lwh = np.array([3.9, 1.6, 1.5]) * rng.uniform(0.5, 2.0, (count_boxes, 1))  # PTSN scales
    # centres 1-150 m beyond the box's own reach: the sensor is always outside
    distance = np.geomspace(1.0, 150.0, count_boxes) + 0.5 * np.linalg.norm(lwh, axis=1)
    azimuth = rng.uniform(-np.pi, np.pi, count_boxes)
    boxes = np.column_stack(
        [
            distance * np.cos(azimuth),
            distance * np.sin(azimuth),
            rng.uniform(-1.5, 0.5, count_boxes),
            lwh,
            rng.uniform(-np.pi, np.pi, count_boxes),
        ]
    )
    from dali_cli.ppcg.fitting import model_to_sensor

    rays = []
    half = rays_per_box // 2
    for box in boxes:
        pick = edges[rng.integers(0, len(edges), half)]
        along = rng.uniform(0.05, 0.95, (half, 1))
        on_edges = vertices[pick[:, 0]] * (1 - along) + vertices[pick[:, 1]] * along
        inside = rng.uniform(-0.49, 0.49, (rays_per_box - half, 3))
        targets = model_to_sensor(np.concatenate([on_edges, inside]), box)
        rays.append(targets / np.linalg.norm(targets, axis=1, keepdims=True))
    bounds = np.r_[0, np.cumsum([len(r) for r in rays])]
    # rays aimed at an edge on the far side of the box hit the near side first: fine, the
    # reference is the first hit of each ray. Rays that only touch the box (a chord under
    # 1 mm, at a cube edge) have no well-defined answer and are left out.
    directions = np.concatenate(rays)
    keep = analytic_first_hit(boxes, directions, bounds, chord=True) > 1e-3
    counts = np.add.reduceat(keep.astype(np.int64), bounds[:-1])
    return boxes, directions[keep], np.r_[0, np.cumsum(counts)]


def analytic_first_hit(boxes, directions, bounds, chord: bool = False) -> np.ndarray:
    """float64 distance `(N,)` from the sensor to each ray's entry into its box (inf: miss);
    `chord`: the length of the ray inside the box instead."""
    from dali_cli.ppcg.fitting import rays_to_model

    out = np.full(len(directions), np.inf)
    for b, box in enumerate(boxes):
        segment = slice(bounds[b], bounds[b + 1])
        origin, local = rays_to_model(np.zeros(3), directions[segment], box)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-0.5 - origin) / local, (0.5 - origin) / local
        near = np.nanmax(np.minimum(t1, t2), axis=1)
        far = np.nanmin(np.maximum(t1, t2), axis=1)
        entry = np.where((far >= near) & (far > 0), np.maximum(near, 0.0), np.inf)
        out[segment] = np.where(np.isfinite(entry), far - near, 0.0) if chord else entry
    return out


def bank_of(scene, vertices, faces):
    """A one-model PPCG ModelBank that traces `scene` (instead of the cached robust BVH)."""
    from dali_cli.ppcg.models import ModelBank

    bank = ModelBank("cad", ["box"], [[1.0, 1.0, 1.0]], meshes=[(vertices, faces)])
    bank._bvhs[0] = scene
    return bank


def cast(scene, boxes, directions, bounds, setup: str) -> tuple[np.ndarray, np.ndarray]:
    """Hit `(N,)` and points `(N, 3)` float64 of every ray with one set-up (module doc); for
    "float64" `scene` is a bank_of(...)."""
    if setup == "float64":
        return scene.cast_many(np.zeros(len(boxes), np.int64), boxes, directions, bounds, 0.0)
    from dali_cli.ppcg.fitting import box_affine_inverse

    hit = np.zeros(len(directions), bool)
    points = np.full((len(directions), 3), np.nan)
    for b, box in enumerate(boxes):
        a, z = bounds[b], bounds[b + 1]
        inverse = box_affine_inverse(box).astype(np.float32)
        origin = inverse @ (-box[:3]).astype(np.float32)
        sensor_dirs = directions[a:z].astype(np.float32)
        local = np.ascontiguousarray(sensor_dirs @ inverse.T)
        origins = np.ascontiguousarray(np.broadcast_to(origin, local.shape))
        far = np.full(z - a, 1e30, np.float32)
        result = scene._trace(origins, local, far)
        hit[a:z] = result["geomID"] >= 0
        points[a:z] = (result["tfar"][:, None] * sensor_dirs).astype(np.float64)
    points[~hit] = np.nan
    return hit, points


def measure(repeats: int, boxes: int = 120, rays_per_box: int = 400, seed: int = 0) -> list[dict]:
    """One point per (robust, setup): error against the analytic hits and rays/s (median)."""
    vertices, faces, _ = unit_box_mesh()
    box_array, directions, bounds = make_rays(boxes, rays_per_box, seed)
    exact = analytic_first_hit(box_array, directions, bounds)
    assert np.isfinite(exact).all()
    points = []
    for robust in (True, False):
        scene = _Scene(vertices, faces, robust)
        for setup in ("float64", "float32"):
            target = bank_of(scene, vertices, faces) if setup == "float64" else scene
            cast(target, box_array, directions, bounds, setup)  # warm-up
            walls = []  # CPU seconds of this thread (Embree traces on it): steadier under load
            for _ in range(repeats):
                started = time.thread_time()
                hit, xyz = cast(target, box_array, directions, bounds, setup)
                walls.append(time.thread_time() - started)
            error = np.abs(np.linalg.norm(xyz, axis=1) - exact)  # along the ray, m
            error_all = np.where(hit, error, np.inf)  # a miss is an unbounded error
            far = np.linalg.norm(box_array[:, :2], axis=1) > 100.0
            far_rays = np.repeat(far, np.diff(bounds))
            good = hit & (error < 0.01)  # a hit on the right face (1 cm: not another face)
            seconds = float(np.median(walls))
            points.append(
                {
                    "robust": robust,
                    "setup": setup,
                    "default": robust == DEFAULT["robust"] and setup == DEFAULT["setup"],
                    "rays": int(len(directions)),
                    "rays_per_cpu_second": round(len(directions) / seconds),
                    "cpu_seconds_median": round(seconds, 5),
                    "all_seconds": [round(w, 5) for w in walls],
                    "missed_fraction": float(1.0 - hit.mean()),
                    "wrong_face_fraction": float((hit & ~good).mean()),
                    "error_mm_median": float(np.median(error[good]) * 1e3),
                    "error_mm_p99": float(np.percentile(error[good], 99) * 1e3),
                    "error_mm_p99_beyond_100m": float(
                        np.percentile(error[good & far_rays], 99) * 1e3
                    ),
                    "error_mm_max": float(error[good].max() * 1e3),
                    # all rays: wrong-face hits count with their error, misses as infinite
                    "error_mm_p999_all_rays": float(np.percentile(error_all, 99.9) * 1e3),
                }
            )
    return points
