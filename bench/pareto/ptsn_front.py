"""PTSN front: grid step, bracket vs grid, frame subsample -> |ŝ - ŝ_ref| vs detector passes and s.

ŝ_ref is the full grid (0.8:1.4 step 0.01, the default resolution) on every frame. Each variant
runs dali_cli.ptsn.find_scale exactly as `dali ptsn-sweep` does, on its own detection cache (so
its frame passes are its own) backed by one shared store: a (frame, scale) pair is run through
the detector once for all variants. A variant's seconds are its frame passes times the median
measured seconds of one frame pass (the detector's cost does not depend on who asked).
"""

from __future__ import annotations

import numpy as np

DEFAULT = {"search": "bracket", "step": 0.01, "frames": None, "subsample_min": 16}


def _shared_cache_class():
    from dali_cli import ptsn

    class SharedCache(ptsn.DetectionCache):
        """A DetectionCache that counts its own passes but takes detections from `shared`."""

        def __init__(self, shared: ptsn.DetectionCache):
            super().__init__(
                shared.detector, shared.frames, shared.score_min, shared.mount_height_m
            )
            self.shared = shared

        def detections(self, scale, indices):
            scale = self.key(scale)
            missing = [int(i) for i in indices if (int(i), scale) not in self._store]
            if missing:
                for index, found in zip(
                    missing, self.shared.detections(scale, missing), strict=True
                ):
                    self._store[(index, scale)] = found
                self.frame_passes += len(missing)
            return [self._store[(int(i), scale)] for i in indices]

    return SharedCache


def load_frames(model_dir, target_dir, scale_low: float, scale_high: float, limit=None):
    """The detector and the target's (first `limit`) frames cropped as ptsn-sweep crops them."""
    from dali_cli import ptsn
    from dali_cli.detector import Detector
    from dali_cli.store.artifacts import FrameSet

    detector = Detector.load(model_dir)
    frames = [
        ptsn.crop_for_scales(points, detector.visible_range, scale_low, scale_high)
        for _, points in FrameSet(target_dir).iter_frames()
    ][:limit]
    return detector, frames


def measure(
    model_dir, target_dir, sensor: str, quick: bool = False, frames=None, first_stage_only=True
) -> dict:
    """The front; `first_stage_only`: run the detector without its second stage (cheaper frame
    passes; the search strategies compare the same either way)."""
    import dataclasses
    import time

    from dali_cli import ptsn
    from dali_cli.sensors import get_profile

    low, high = 0.8, 1.4
    detector, frames = load_frames(model_dir, target_dir, low, high, frames)
    if first_stage_only:
        detector.config = dataclasses.replace(detector.config, refine=False)
    profile = get_profile(sensor)
    target_lwh = np.asarray(profile.car_mean_lwh_m, np.float64)
    shared = ptsn.DetectionCache(detector, frames, score_min=0.3, mount_height_m=None)
    SharedCache = _shared_cache_class()
    everything = np.arange(len(frames), dtype=np.int64)

    def run(
        search: str, step: float, frames_used, subsample_min: int, fraction=0.25, seed=0
    ) -> dict:
        indices = (
            everything
            if frames_used is None
            else ptsn.select_frames(len(frames), frames_used, None, seed=0)
        )
        subsample = ptsn.subsample_for_bracket(indices, fraction, subsample_min, seed=seed)
        cache = SharedCache(shared)
        started = time.perf_counter()
        result = ptsn.find_scale(
            cache,
            ptsn.ScaleRange(low, high, step),
            target_lwh,
            indices,
            search=search,
            subsample=subsample,
            no_detections="identity",
        )
        return {
            "search": search,
            "step": step,
            "frames": len(indices),
            "subsample_frames": len(subsample) if search == "bracket" else None,
            "scale": result.scale,
            "fallback": result.fallback,
            "frame_passes": cache.frame_passes,
            "wall_seconds_incl_shared_passes": round(time.perf_counter() - started, 2),
        }

    variants = [("grid", 0.01, None, 16)]  # the reference first: it fills the shared store
    if not quick:
        variants += [("grid", 0.02, None, 16), ("grid", 0.05, None, 16)]
    variants += [("bracket", 0.01, None, 16), ("bracket", 0.02, None, 16)]
    if not quick:
        variants += [("bracket", 0.05, None, 16), ("bracket", 0.01, None, 8)]
        variants += [
            ("bracket", 0.01, n, min(16, n)) for n in (len(frames) // 4, len(frames) // 2) if n
        ]
    points = [run(*variant) for variant in variants]
    per_pass = shared.seconds / max(shared.frame_passes, 1)
    reference = points[0]["scale"]
    for point, (search, step, frames_used, subsample_min) in zip(points, variants, strict=True):
        point["default"] = (
            search == DEFAULT["search"]
            and step == DEFAULT["step"]
            and frames_used == DEFAULT["frames"]
            and subsample_min == DEFAULT["subsample_min"]
        )
        point["scale_error"] = abs(point["scale"] - reference)
        point["seconds"] = round(point["frame_passes"] * per_pass, 2)
    robustness = [] if quick else subsample_robustness(run, reference, len(frames))
    return {
        "detector_first_stage_only": first_stage_only,
        "subsample_robustness": robustness,
        "reference_scale": reference,
        "frames": len(frames),
        "seconds_per_frame_pass": round(per_pass, 4),
        "detector_frame_passes_run": shared.frame_passes,
        "points": points,
    }


def subsample_robustness(run, reference: float, frames: int, seeds: int = 10) -> list[dict]:
    """How often the bracket's secant phase on a random subsample of each size still ends at
    the full grid's ŝ (all frames, step 0.01; scales off the grid's points cost new detector
    passes, shared through the store): per size, the share of `seeds` subsamples that do, the
    largest |ŝ - ŝ_ref| and the mean frame passes."""
    rows = []
    for size in sorted({4, 8, 12, 16, 24} & set(range(1, frames))):
        found = [
            run("bracket", 0.01, None, size, fraction=1e-9, seed=seed) for seed in range(seeds)
        ]
        errors = [abs(point["scale"] - reference) for point in found]
        rows.append(
            {
                "subsample_frames": size,
                "seeds": seeds,
                "exact_share": sum(error < 0.005 for error in errors) / seeds,
                "max_scale_error": round(max(errors), 4),
                "mean_frame_passes": round(float(np.mean([p["frame_passes"] for p in found])), 1),
            }
        )
    return rows
