"""Benchmark inputs built in memory: synthetic frames with jittered labels as pseudo boxes, and
procedural car libraries at a chosen mesh detail."""

from __future__ import annotations

import numpy as np


def jittered_frames(
    sensor: str, frames: int, seed: int
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """`frames` synthetic frames of `sensor` (dali synth scenes): (frame id, points `(n, 4)`
    float32, pseudo boxes `(k, 7)`) where the pseudo boxes are the labeled cars with >= 5 points,
    jittered as a detector's boxes would be (size +-6 %, centre +-0.15 m, yaw +-3 deg)."""
    from dali_cli.sensors import get_profile
    from dali_cli.synth import synth_frame

    profile = get_profile(sensor)
    rng = np.random.default_rng(seed)
    out = []
    for index in range(frames):
        frame = synth_frame(seed, index, profile, profile)
        jittered = frame.boxes[frame.num_points >= 5].copy()
        count = len(jittered)
        jittered[:, :2] += rng.normal(0, 0.15, (count, 2))
        jittered[:, 3:6] *= rng.uniform(0.94, 1.06, (count, 3))
        jittered[:, 6] += np.radians(rng.normal(0, 3, count))
        jittered[:, 6] = (jittered[:, 6] + np.pi) % (2 * np.pi) - np.pi
        out.append((frame.frame_id, frame.points, jittered))
    return out


def cad_bank(cars: int, lod: int, seed: int = 7):
    """A PPCG ModelBank of `cars` procedural cars of about `lod` triangles each; the same seed
    gives the same cars (shape parameters) at every `lod`."""
    from dali_cli.library import ModelLibrary, procedural_library
    from dali_cli.ppcg.models import ModelBank

    library = ModelLibrary(meshes=procedural_library(cars, seed=seed, lod=lod))
    return ModelBank.from_library(library, "cad", f"procedural-{cars}x{lod}")
