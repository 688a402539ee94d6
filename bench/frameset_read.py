"""Benchmark: the cost of verifying what FrameSet reads (chunk presence + CRC-32C per chunk).

Writes FRAMES KITTI-sized frames (120 k points each) twice, Zstd-compressed and raw: once with
dali's writer (a CRC-32C per chunk) and once with the same layout but no checksum (as a frame set
without checksums), then times `FrameSet.iter_frames` over all frames and `frame()` of
every tenth frame with the same reader (best of REPEATS). The difference is the checksum; the
presence check (one stat per chunk per FrameSet) is in both. Writes
bench/results/frameset_read.json.

    .venv/bin/python bench/frameset_read.py [--frames 100] [--repeats 7]
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
from pathlib import Path

import numpy as np
from pareto.common import best_seconds

from dali_cli.store.artifacts import FRAMES_NAME, FrameSet, FrameSetWriter

RESULTS = Path(__file__).resolve().parent / "results" / "frameset_read.json"
POINTS_PER_FRAME = 120_000


def write(directory: Path, frame: np.ndarray, frames: int, compress: bool, checksum: bool) -> None:
    with FrameSetWriter(directory, sensor="kitti", compress=compress) as writer:
        for i in range(frames):
            writer.append(f"{i:06d}", frame)
    if not checksum:  # rewrite the points array without the CRC codec, same chunks
        import zarr
        from zarr.codecs import ZstdCodec

        group = zarr.open_group(str(directory / FRAMES_NAME), mode="r+")
        values = group["points"][:]
        del group["points"]
        group.create_array(
            "points",
            data=values,
            chunks=(2**21, 4),
            compressors=(ZstdCodec(level=0),) if compress else None,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    frame = (np.random.default_rng(0).normal(size=(POINTS_PER_FRAME, 4)) * 20).astype(np.float32)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for compress in (False, True):
            for checksum in (False, True):
                directory = Path(tmp) / f"c{int(compress)}-k{int(checksum)}"
                write(directory, frame, args.frames, compress, checksum)
                frameset = FrameSet(directory)
                rows.append({
                    "compress": compress,
                    "checksum": checksum,
                    "iter_frames_s": best_seconds(
                        lambda d=directory: sum(1 for _ in FrameSet(d).iter_frames()), args.repeats
                    ),
                    "frame_every_10th_s": best_seconds(
                        lambda f=frameset: [f.frame(i) for i in range(0, args.frames, 10)],
                        args.repeats,
                    ),
                })  # fmt: skip
    points = args.frames * POINTS_PER_FRAME
    for row in rows:
        print(
            f"compress={row['compress']!s:5} checksum={row['checksum']!s:5}: iter_frames "
            f"{row['iter_frames_s'] * 1e3:6.0f} ms ({points / 1e6:.0f} M points), "
            f"frame() x{len(range(0, args.frames, 10))} {row['frame_every_10th_s'] * 1e3:5.0f} ms"
        )
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(
        json.dumps(
            {
                "frames": args.frames,
                "points_per_frame": POINTS_PER_FRAME,
                "repeats": args.repeats,
                "machine": platform.processor() or platform.machine(),
                "rows": rows,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
