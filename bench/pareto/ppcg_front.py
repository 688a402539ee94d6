"""PPCG fronts: mesh detail and library size vs error and ms/frame; the skips and what they save.

Frames: synthetic KITTI-like frames with jittered labels as pseudo boxes (pareto.data). Models:
procedural cars, the same cars (seed) at every mesh detail.

- mesh detail (lod 1k / 5k / 8k / 20k / 67k triangles per car, the library's size fixed): the RC
  rays of every eligible box are cast on the car at each detail and at the full detail (67k,
  the reference), the model chosen by the full library for both. Surface error: |t - t_full|
  along each ray that hits both (mm); box-fit error: the mean |extent - extent_full| over l, w,
  h of the box-frame bounding box of each box's hits (mm); miss change: rays whose hit/miss
  differs. Time: rc_frame and cf_frame compute per frame (CPU ms of the one thread they run on,
  median over repeats; I/O excluded: it does not depend on these knobs) and BVH builds.
- library size (5 / 10 / 24 / 40 cars at lod 8k): size-fit error of the selected model
  (mean over boxes and l, w, h of |model / box - 1|, %) vs the same times.
- CF window on / off: cf_frame with each box's angular window vs every ray of the pattern: the
  new points must be bit-identical; rays cast per frame and ms/frame.
- skips: RC's dense boxes (rays saved; a method choice, output differs by design) and frames
  without boxes (passed through: output identical, ms per frame).
"""

from __future__ import annotations

import hashlib
import time

import numpy as np

DEFAULT_LOD = 8000  # dali library build --procedural's default (library.procedural_library)
DETAIL_LODS = (1000, 5000, DEFAULT_LOD, 20000, 67000)
LIBRARY_SIZES = (5, 10, 24, 40)
DEFAULT_LIBRARY = 24  # the Makefile's LIBRARY_MODELS


def _timed_frames(function, frames, repeats: int) -> tuple[float, list]:
    """Median over repeats of the mean CPU seconds per frame of `function(frame)` (this thread's
    CPU time: PPCG's frame functions run on one thread, and on a shared machine wall time
    mostly measures the other jobs), and the outputs of the last repeat."""
    cpus, outputs = [], None
    for _ in range(repeats):
        started = time.thread_time()
        outputs = [function(frame) for frame in frames]
        cpus.append((time.thread_time() - started) / len(frames))
    return float(np.median(cpus)), outputs


def _warm(bank) -> float:
    """Build every BVH of a bank now, bypassing the process-wide cache; returns the CPU seconds."""
    from dali_cli.raycast import MeshBVH

    started = time.thread_time()
    for index, (vertices, faces) in enumerate(bank.meshes):
        bank._bvhs[index] = MeshBVH.from_mesh(vertices, faces)
    return time.thread_time() - started


def _rc_rays(frame, params):
    """(boxes (B, 7), car-point rays (N, 3), bounds (B + 1,)) of the boxes RC re-casts."""
    from dali_cli.ppcg.frame import car_points, ground_heights

    _, points, boxes = frame
    ground_z = ground_heights(boxes, params.mount_height_m, params.ground_margin_m)
    members, _ = car_points(points, boxes, ground_z)
    counts = np.array([len(m) for m in members])
    eligible = np.flatnonzero((counts >= params.min_points) & (counts < params.max_points))
    rays = [points[members[i], :3].astype(np.float64) for i in eligible]
    bounds = np.r_[0, np.cumsum([len(r) for r in rays])]
    directions = np.concatenate(rays) if rays else np.zeros((0, 3))
    return boxes[eligible], directions, bounds


def _box_extents(xyz, box) -> np.ndarray:
    """l, w, h `(3,)` of the box-frame bounding box of points `(n, 3)`."""
    cos, sin = np.cos(box[6]), np.sin(box[6])
    local = (xyz - box[:3]) @ np.array([[cos, -sin, 0], [sin, cos, 0], [0, 0, 1.0]])
    return local.max(axis=0) - local.min(axis=0)


def _params(sensor: str):
    from dali_cli.ppcg.cf import CfParams
    from dali_cli.ppcg.point_models import angular_threshold_rad
    from dali_cli.ppcg.rc import RcParams
    from dali_cli.sensors import get_profile

    profile = get_profile(sensor)
    theta = angular_threshold_rad(profile.points_per_beam)
    return (
        profile,
        RcParams(mount_height_m=profile.mount_height_m, theta_rad=theta),
        CfParams(theta_rad=theta),
    )


def _stage_times(bank, frames, profile, rc_params, cf_params, repeats):
    from dali_cli.ppcg.cf import cf_frame
    from dali_cli.ppcg.rc import rc_frame

    rc, _ = _timed_frames(lambda f: rc_frame(f[0], f[1], f[2], bank, rc_params), frames, repeats)
    cf, _ = _timed_frames(
        lambda f: cf_frame(f[0], f[1], f[2], bank, profile, cf_params), frames, repeats
    )
    return rc, cf


def mesh_detail(frames, sensor: str, cars: int, repeats: int) -> list[dict]:
    from pareto.data import cad_bank

    profile, rc_params, cf_params = _params(sensor)
    reference = cad_bank(cars, DETAIL_LODS[-1])
    reference_build = _warm(reference)
    cast_sets = [_rc_rays(frame, rc_params) for frame in frames]
    chosen = [reference.select(boxes) for boxes, _, _ in cast_sets]

    def cast_all(bank):
        return [
            bank.cast_many(models, boxes, rays, bounds, rc_params.theta_rad)
            for models, (boxes, rays, bounds) in zip(chosen, cast_sets, strict=True)
        ]

    full = cast_all(reference)
    points = []
    for lod in DETAIL_LODS:
        bank = reference if lod == DETAIL_LODS[-1] else cad_bank(cars, lod)
        build = _warm(bank) if bank is not reference else reference_build
        triangles = float(np.mean([len(faces) for _, faces in bank.meshes]))
        errors, fits, changed, rays = [], [], 0, 0
        for (hit, xyz), (hit_full, xyz_full), (boxes, _, bounds) in zip(
            cast_all(bank), full, cast_sets, strict=True
        ):
            both = hit & hit_full
            errors.append(np.linalg.norm(xyz[both] - xyz_full[both], axis=1))
            changed += int((hit != hit_full).sum())
            rays += len(hit)
            for b, box in enumerate(boxes):
                segment = slice(bounds[b], bounds[b + 1])
                ok = both[segment]
                if ok.sum() >= 3:
                    fits.append(
                        np.abs(
                            _box_extents(xyz[segment][ok], box)
                            - _box_extents(xyz_full[segment][ok], box)
                        ).mean()
                    )
        error = np.concatenate(errors)
        rc, cf = _stage_times(bank, frames, profile, rc_params, cf_params, repeats)
        points.append(
            {
                "lod": lod,
                "default": lod == DEFAULT_LOD,
                "mean_triangles": round(triangles),
                "cars": cars,
                "surface_error_mm_median": float(np.median(error) * 1e3),
                "surface_error_mm_p95": float(np.percentile(error, 95) * 1e3),
                "box_fit_error_mm_mean": float(np.mean(fits) * 1e3),
                "hit_changed_fraction": changed / max(rays, 1),
                "rays": rays,
                "rc_cpu_ms_per_frame": rc * 1e3,
                "cf_cpu_ms_per_frame": cf * 1e3,
                "bvh_build_seconds_whole_library": None if build is None else round(build, 3),
            }
        )
    return points


def library_size(frames, sensor: str, lod: int, repeats: int) -> list[dict]:
    from pareto.data import cad_bank

    profile, rc_params, cf_params = _params(sensor)
    boxes = np.concatenate([f[2] for f in frames])
    points = []
    for cars in LIBRARY_SIZES:
        bank = cad_bank(cars, lod)
        build = _warm(bank)
        chosen = bank.lwh[bank.select(boxes)]
        misfit = np.abs(chosen / boxes[:, 3:6] - 1.0).mean()
        rc, cf = _stage_times(bank, frames, profile, rc_params, cf_params, repeats)
        points.append(
            {
                "cars": cars,
                "lod": lod,
                "default": cars == DEFAULT_LIBRARY,
                "size_fit_error_percent": float(misfit * 100),
                "rc_cpu_ms_per_frame": rc * 1e3,
                "cf_cpu_ms_per_frame": cf * 1e3,
                "bvh_build_seconds_whole_library": round(build, 3),
            }
        )
    return points


def _digest(outputs) -> str:
    digest = hashlib.sha256()
    for new, records in outputs:
        digest.update(np.ascontiguousarray(new).tobytes())
        digest.update(records.points_after.tobytes())
    return digest.hexdigest()


def cf_window(frames, sensor: str, lod: int, cars: int, repeats: int) -> list[dict]:
    """cf_frame with and without the angular windows (module doc)."""
    from dali_cli.ppcg import cf as cf_module
    from dali_cli.ppcg.window import _direction_table
    from pareto.data import cad_bank

    profile, _, cf_params = _params(sensor)
    bank = cad_bank(cars, lod)
    _warm(bank)
    counted = {"rays": 0}
    windowed = cf_module.windows_directions

    def every_ray(profile, windows):
        table = _direction_table(profile)
        count = len(windows)
        return np.tile(table, (count, 1)), np.arange(count + 1, dtype=np.int64) * len(table)

    points = []
    for name, directions_of in (("window", windowed), ("every ray", every_ray)):

        def counting(profile, windows, directions_of=directions_of):
            directions, bounds = directions_of(profile, windows)
            counted["rays"] += len(directions)
            return directions, bounds

        runs = repeats if name == "window" else 1  # every ray: ~1 s per frame
        cf_module.windows_directions = counting
        try:
            counted["rays"] = 0
            seconds, outputs = _timed_frames(
                lambda f: cf_module.cf_frame(f[0], f[1], f[2], bank, profile, cf_params),
                frames,
                runs,
            )
            rays = counted["rays"] / (runs * len(frames))
        finally:
            cf_module.windows_directions = windowed
        points.append(
            {
                "mode": name,
                "default": name == "window",
                "cf_cpu_ms_per_frame": seconds * 1e3,
                "rays_per_frame": rays,
                "points_sha256": _digest(outputs),
            }
        )
    points[1]["identical_to_window"] = points[1]["points_sha256"] == points[0]["points_sha256"]
    return points


def skips(frames, sensor: str, lod: int, cars: int, repeats: int) -> dict:
    """What RC's dense-box skip and the pass-through of frames without boxes save."""
    from dali_cli.ppcg.driver import Job, _Worker
    from dali_cli.ppcg.rc import rc_frame
    from pareto.data import cad_bank

    profile, rc_params, _ = _params(sensor)
    bank = cad_bank(cars, lod)
    _warm(bank)
    dense_rays = recast_rays = 0
    for frame_id, points, boxes in frames:
        _, records = rc_frame(frame_id, points, boxes, bank, rc_params)
        dense_rays += int(records.points_before[records.reason == "dense"].sum())
        recast_rays += int(records.points_before[records.ppcg == "rc"].sum())
    # a frame without boxes: the driver passes it through (no in-box test, no casts)
    worker = _Worker.__new__(_Worker)
    worker.job = Job("rc", "", "", "cad", sensor, None, rc_params)
    worker.bank, worker.profile = bank, profile
    empty = np.zeros((0, 7))
    seconds, outputs = _timed_frames(lambda f: worker.process(f[0], f[1], empty), frames, repeats)
    unchanged = all(
        out.points is frame[1] or np.array_equal(out.points, frame[1])
        for out, frame in zip(outputs, frames, strict=True)
    )
    with_boxes, _ = _timed_frames(lambda f: worker.process(f[0], f[1], f[2]), frames, repeats)
    return {
        "rc_dense_boxes": {
            "rays_saved_per_frame": dense_rays / len(frames),
            "rays_cast_per_frame": recast_rays / len(frames),
            "output_unchanged": False,
            "note": "dense boxes keep their raw points by the method's design (RC for sparse "
            "boxes only), so the skip defines the output rather than preserving another one",
        },
        "frames_without_boxes": {
            "compute_cpu_ms_per_frame": seconds * 1e3,
            "compute_cpu_ms_per_frame_with_boxes": with_boxes * 1e3,
            "output_unchanged": bool(unchanged),
        },
    }
