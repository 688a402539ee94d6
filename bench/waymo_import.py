"""Import speed of `dali import waymo` (v2 Parquet and v1 TFRecord) on a synthetic segment of
real size: TOP 64 x 2650 range images with both returns and a per-pixel pose, one 200 x 600
short-range lidar (FRONT), 3 boxes per frame (30 % of the pixels return). Writes bench/results/waymo_import.json.

    .venv/bin/python bench/waymo_import.py [--frames 20]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import tests.test_waymo as fixture  # noqa: E402  (the test's writers, at real sizes)


def cpu_model() -> str:
    from dali_cli.runtime.machine import cpu_model as model

    return model()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=20)
    args = parser.parse_args()
    fixture.TOP_W = 2650
    fixture.FRONT_H, fixture.FRONT_W = 200, 600
    rng = np.random.default_rng(0)
    frames = []
    for index in range(args.frames):
        stamp = 1_550_000_000_000_000 + 100_000 * index
        top1 = fixture.synthetic_scan(rng, 64, 2650, fixture.TOP_EXTRINSIC,
                                      fixture.TOP_INCLINATIONS, index % 3, True)  # fmt: skip
        top2 = fixture.synthetic_scan(rng, 64, 2650, fixture.TOP_EXTRINSIC,
                                      fixture.TOP_INCLINATIONS, index % 3, True)  # fmt: skip
        front = fixture.synthetic_scan(
            rng, 200, 600, fixture.FRONT_EXTRINSIC,
            fixture.uniform_inclinations(np.radians(-90.0), np.radians(30.0), 200), 0, False,
        )  # fmt: skip
        frames.append({"stamp": stamp, "top1": top1, "top2": top2, "front": front})
    fixture.STAMPS = tuple(f["stamp"] for f in frames)
    results = {
        "machine": {"cpu_model": cpu_model(), "cores": os.cpu_count(),
                    "load_average_1min": os.getloadavg()[0], "python": platform.python_version()},
        "frames": args.frames,
        "command": f"bench/waymo_import.py --frames {args.frames}",
    }  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        roots = {"v2": fixture.write_v2(tmp / "v2", frames, row_group_size=8),
                 "v1": fixture.write_v1(tmp / "v1", frames)}  # fmt: skip
        for fmt, root in roots.items():
            for lidars in ("top", "all"):
                out = tmp / f"out-{fmt}-{lidars}"
                started = time.perf_counter()
                result = fixture.run_import(root, out, "--lidars", lidars, "--returns", "2")
                seconds = time.perf_counter() - started
                assert result.exit_code == 0, result.output
                manifest = json.loads((out / "manifest.json").read_text())
                results[f"{fmt}_{lidars}"] = {
                    "seconds": round(seconds, 3),
                    "frames_per_s": round(args.frames / seconds, 2),
                    "points_per_frame": manifest["outputs"]["counts"]["points"] // args.frames,
                }
                print(fmt, lidars, results[f"{fmt}_{lidars}"])
    results["load_average_1min_end"] = os.getloadavg()[0]
    out = ROOT / "bench" / "results" / "waymo_import.json"
    out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
