"""Benchmark: import / export throughput on copies of the real KITTI and nuScenes fixture frames.

Builds a KITTI root with FRAMES copies of frame 000008 (velodyne, label_2, calib) and a directory
of FRAMES copies of the nuScenes sweep with a CSV naming each box's frame, then times
`dali import kitti`, `dali export kitti` (of the imported labels), `dali import nuscenes` and
`dali view`, in-process (no subprocess start-up), and reports seconds per frame and points per
second. Beam removal: `dali import kitti --beams 16` of the same copies and, with `--drive`, `dali
import kitti-raw` of a whole raw drive (full 360-degree scans, about 120,000 points each) plain
and with `--beams 16`; `beams16_cost` is each pair's ratio (the KITTI pair after a first, warm-up import) of seconds per scan (target: <= 2).
Writes bench/results/importers.json.

    .venv/bin/python bench/importers.py [--frames 50] [--drive raw/2011_09_26/2011_09_26_drive_0001_sync]
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

from click.testing import CliRunner

from dali_cli.runtime.machine import cpu_model

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results" / "importers.json"
NUSCENES_SCAN = (
    DATA / "nuscenes" / "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
)


def timed(*arguments) -> float:
    from dali_cli.cli import main

    started = time.perf_counter()
    result = CliRunner().invoke(main, [str(a) for a in arguments])
    seconds = time.perf_counter() - started
    if result.exit_code != 0:
        sys.exit(f"dali {' '.join(map(str, arguments))} failed:\n{result.output}")
    return seconds


def kitti_root(base: Path, frames: int) -> Path:
    root = base / "kitti" / "training"
    for part in ("velodyne", "label_2", "calib"):
        (root / part).mkdir(parents=True)
        source = next((DATA / "kitti" / "training" / part).iterdir())
        for i in range(frames):
            shutil.copy(source, root / part / f"{i:06d}{source.suffix}")
    return root.parent


def nuscenes_dir(base: Path, frames: int) -> tuple[Path, Path]:
    directory = base / "nuscenes"
    directory.mkdir()
    with open(DATA / "nuscenes" / "boxes_lidar.csv") as handle:
        reader = csv.DictReader(handle)
        rows, header = list(reader), reader.fieldnames
    csv_path = base / "boxes.csv"
    with open(csv_path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=[*header, "frame_id"])
        writer.writeheader()
        for i in range(frames):
            shutil.copy(NUSCENES_SCAN, directory / f"sweep{i:04d}.pcd.bin")
            writer.writerows({**row, "frame_id": f"sweep{i:04d}"} for row in rows)
    return directory, csv_path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--drive", type=Path, default=None, help="a KITTI raw synced drive")
    args = parser.parse_args()
    if not NUSCENES_SCAN.is_file():
        sys.exit(f"fixtures not found under {DATA}")
    with tempfile.TemporaryDirectory() as temporary:
        base = Path(temporary)
        kitti = kitti_root(base, args.frames)
        nus, nus_csv = nuscenes_dir(base, args.frames)
        seconds = {
            "import_kitti": timed("import", "kitti", kitti, "--out", base / "k"),
            "export_kitti": timed(
                "export",
                "kitti",
                base / "k",
                "--calib-root",
                kitti,
                "--project-bbox",
                "--out",
                base / "e",
            ),  # fmt: skip
            "import_nuscenes_csv": timed(
                "import", "nuscenes", nus, "--boxes-csv", nus_csv, "--out", base / "n"
            ),
            "view_nuscenes_frame": timed(
                "view", base / "n", "--frame", "0", "--side", "--out", base / "v.png"
            ),
            # the pair compared runs warm (the first import above also loads the modules)
            "import_kitti_again": timed("import", "kitti", kitti, "--out", base / "k2"),
            "import_kitti_again_beams16": timed(
                "import", "kitti", kitti, "--beams", "16", "--out", base / "k16"
            ),
        }
        scans = {key: args.frames for key in seconds}
        if args.drive is not None:
            drive = ["import", "kitti-raw", args.drive, "--no-labels"]
            seconds["import_kitti_raw"] = timed(*drive, "--out", base / "r")
            seconds["import_kitti_raw_beams16"] = timed(
                *drive, "--beams", "16", "--out", base / "r16"
            )
            count = len(list((args.drive / "velodyne_points" / "data").glob("*.bin")))
            scans.update(import_kitti_raw=count, import_kitti_raw_beams16=count)
    points = {"import_kitti": 17238 * args.frames, "import_nuscenes_csv": 34688 * args.frames}
    result = {
        "benchmark": "importers",
        "frames": args.frames,
        "machine": {
            "python": platform.python_version(),
            "cpu": cpu_model(),  # dali_cli.runtime.machine
        },
        "seconds": {k: round(v, 3) for k, v in seconds.items()},
        "seconds_per_frame": {
            k: round(v / scans[k], 4) for k, v in seconds.items() if k != "view_nuscenes_frame"
        },
        "beams16_cost": {
            plain: round(seconds[f"{plain}_beams16"] / seconds[plain], 2)
            for plain in ("import_kitti_again", "import_kitti_raw")
            if plain in seconds
        },
        "points_per_second": {k: round(points[k] / seconds[k]) for k in points},
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
