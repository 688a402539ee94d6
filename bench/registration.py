"""Benchmark: scan registration by dali's own ICP (dali_cli.registration) against KISS-ICP
(the `kiss-icp` package, Vizzo et al., RA-L 2023) on drives of a known street.

The street of tests/street_scans.py (ground, building fronts with gaps and setbacks, poles,
parked cars; 32 beams, 360 degrees, 1 cm range noise) scanned along three trajectories whose
poses are known: a steady drive (1.2 m a scan, weaving by +-6 degrees), a drive speeding up from
0.2 to 1.8 m a scan (weaving the same), and stop-and-go (steps of 0 to 1.5 m, straight). Both registrations see the same
scans, one thread each, pinned to one core; KISS-ICP with its defaults but deskewing (the
synthetic scans are taken at one instant) and with dali's range window (3-80 m). Per drive: the
end drift (m and % of the path), the median and largest per-step translation (cm) and rotation
(deg) errors, and the wall time. A third row gives KISS-ICP the scans without their ground
(points above -1.5 m): its point-to-point residuals match a scan's ground rings to the map's
rings where the sensor was, which holds the pose still on this street's flat ground. Writes bench/results/registration.json.

    .venv/bin/python bench/registration.py [--scans 80]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from pareto.common import load_average, machine, pin_one_core

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the street scenes
from street_scans import scan, step_errors, trajectory  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "registration.json"
GROUND_CUT_M = -1.5  # the street's ground is at -1.73 m in the LiDAR frame


def weaving(steps_m: np.ndarray, amplitude_rad: float = 0.1) -> np.ndarray:
    """`(n, 4, 4)` poses along the street: forward steps `steps_m` `(n - 1,)` (m), the heading
    weaving by +-`amplitude_rad` over the drive (so the sensor stays in its lane)."""
    return trajectory(
        steps_m, yaw=amplitude_rad * np.sin(np.linspace(0, 2 * np.pi, len(steps_m) + 1))
    )


def drives(scans: int) -> dict[str, np.ndarray]:
    """name -> `(scans, 4, 4)` true sensor poses of the three drives."""
    n = scans - 1
    stop_and_go = np.clip(1.5 * np.sin(np.linspace(0, 3 * np.pi, n)), 0.0, None)
    return {
        "steady": weaving(np.full(n, 1.2)),
        "speeding-up": weaving(np.linspace(0.2, 1.8, n)),
        "stop-and-go": weaving(stop_and_go, amplitude_rad=0.0),
    }


def register_dali(scans: list[np.ndarray]) -> np.ndarray:
    from dali_cli.registration import RegistrationParams, register_scans

    return register_scans(len(scans), lambda i: scans[i], RegistrationParams()).poses


def register_kiss(scans: list[np.ndarray], ground_cut_m: float | None = None) -> np.ndarray:
    """KISS-ICP's poses of `scans`; `ground_cut_m`: drop the points below this height (m, in
    the LiDAR frame) first."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    config = KISSConfig()
    config.data.deskew = False
    config.data.min_range, config.data.max_range = 3.0, 80.0
    config.registration.max_num_threads = 1
    config.mapping.voxel_size = 1.0
    odometry = KissICP(config)
    poses = []
    for points in scans:
        points = points[:, :3].astype(np.float64)
        if ground_cut_m is not None:
            points = points[points[:, 2] > ground_cut_m]
        odometry.register_frame(points, np.zeros(0))
        poses.append(odometry.last_pose.copy())
    poses = np.asarray(poses)
    return np.linalg.inv(poses[0]) @ poses


def measure(name: str, register, scans: list[np.ndarray], truth: np.ndarray) -> dict:
    started = time.perf_counter()
    poses = register(scans)
    seconds = time.perf_counter() - started
    translation, rotation = step_errors(poses, truth)
    path = float(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum())
    drift = float(np.linalg.norm(poses[-1, :3, 3] - truth[-1, :3, 3]))
    return {
        "registration": name,
        "path_m": round(path, 2),
        "end_drift_m": round(drift, 4),
        "end_drift_percent": round(100 * drift / path, 3),
        "step_translation_cm_median": round(100 * float(np.median(translation)), 2),
        "step_translation_cm_max": round(100 * float(translation.max()), 2),
        "step_rotation_deg_median": round(float(np.median(rotation)), 4),
        "step_rotation_deg_max": round(float(rotation.max()), 4),
        "seconds": round(seconds, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=80, help="scans per drive")
    args = parser.parse_args()
    pin_one_core()
    rows = []
    for drive, truth in drives(args.scans).items():
        scans = [scan(pose, seed=i) for i, pose in enumerate(truth)]
        for name, register in (
            ("dali", register_dali),
            ("kiss-icp", register_kiss),
            ("kiss-icp, ground cut", lambda scans: register_kiss(scans, GROUND_CUT_M)),
        ):
            row = {"drive": drive, "scans": len(scans), **measure(name, register, scans, truth)}
            rows.append(row)
            print(
                f"{drive:12s} {name:21s} drift {row['end_drift_m']:.3f} m "
                f"({row['end_drift_percent']:.2f} % of {row['path_m']:.0f} m), step "
                f"{row['step_translation_cm_median']:.1f} / {row['step_translation_cm_max']:.1f} cm, "
                f"{row['step_rotation_deg_median']:.3f} / {row['step_rotation_deg_max']:.3f} deg, "
                f"{row['seconds']:.1f} s"
            )
    import kiss_icp

    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps({
        "machine": machine(threads=1), "load_average": load_average(),
        "kiss_icp_version": kiss_icp.__version__, "rows": rows,
    }, indent=2) + "\n")  # fmt: skip
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
