"""The point fit's pose search on real pseudo boxes (not a test): CPU seconds of best_pose over
every box of a pseudo-label output that has enough candidate points, for each block schedule
asked for, each checked to pick the same pose as the first (the shipped PRUNE_BLOCKS unless
told). One thread, one process; interleave schedules with --rounds.

Usage:
  .venv/bin/python bench/pose_search_speed.py --data FRAMESET --boxes PSEUDO_DIR \
      [--blocks "8x17,4x6,2x2" --blocks "4x17,2x6"] [--rounds 2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from dali_cli.labels import pose_search
from dali_cli.labels.box_fit import PointFit, candidate_points
from dali_cli.runtime.machine import cpu_model
from dali_cli.store.artifacts import FrameSet
from dali_cli.store.box_tables import read_boxes


def parse_blocks(text: str) -> tuple[tuple[int, int], ...]:
    """'8x17,4x6' -> ((8, 17), (4, 6))."""
    return tuple(tuple(int(n) for n in part.split("x")) for part in text.split(","))


def cases(data: str, boxes: str, fit: PointFit) -> list[tuple[np.ndarray, np.ndarray]]:
    """(candidate points (n, 2), half length and width (2,)) of every box with enough points."""
    table, frames = read_boxes(boxes), FrameSet(data)
    rows, found = table.rows_by_frame(), []
    for frame_id, points in frames.iter_frames():
        if frame_id in rows:
            frame_boxes = table.boxes[rows[frame_id]]
            for k, uv in enumerate(candidate_points(frame_boxes, points, fit)):
                if len(uv) >= fit.min_points:
                    found.append((uv, frame_boxes[k, 3:5] / 2))
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--boxes", required=True)
    parser.add_argument("--blocks", action="append", type=parse_blocks)
    parser.add_argument("--rounds", type=int, default=1)
    args = parser.parse_args()
    fit, schedules = PointFit(), args.blocks or [pose_search.PRUNE_BLOCKS]
    boxes = cases(args.data, args.boxes, fit)
    print(
        f"{cpu_model()}; {len(boxes)} boxes, {np.mean([len(b[0]) for b in boxes]):.0f} points each"
    )
    reference = None
    for round_ in range(args.rounds):
        for schedule in schedules:
            pose_search.PRUNE_BLOCKS = schedule
            started = time.process_time()
            poses = np.array([pose_search.best_pose(uv, half, fit) for uv, half in boxes])
            seconds = time.process_time() - started
            reference = poses if reference is None else reference
            same = bool((poses == reference).all())
            print(f"round {round_ + 1} blocks {schedule}: {seconds:.2f} CPU s, same poses: {same}")


if __name__ == "__main__":
    main()
