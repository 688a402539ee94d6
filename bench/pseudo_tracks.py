"""Benchmark: do pseudo boxes that persist over a drive's scans make better labels? (a diagnosis)

Reads one pseudo-label directory (`dali pseudo-label` on a drive, best made with a low
--score-min so that the filters have recall to work with), the drive's poses and its *held-back*
labels, and measures precision and recall (cars with >= --min-points points in the detector's
grid, greedy matching by score at BEV IoU > --iou, bench/pseudo_labels.py's rule) at every score
cut of --cuts for each variant:

    raw          the pseudo boxes as written, cut by their own score
    persist-N    boxes whose track (dali_cli.labels.tracks) has >= N hits, cut by their own score
    track-N      the same boxes, cut by their track's mean score
    + size       track-N with every box at its track's median l, w, h
    + static     and parked tracks at their median centre and heading axis
    + fill       and boxes interpolated into the frames a track skipped
    parked       parked cars (tracks that do not move in the world, fragments merged) as one
                 box each, placed in every scan where it holds >= --place-points points, cut by
                 the car's median score; moving tracks' boxes as they are, cut by the track's
                 mean score

and the box tightness of the true positives of each (median |error| of the centre along the
range, of l, and of yaw modulo pi). The poses are the drive's OXTS records
(dali_cli.importers.oxts) or a `(n, 4, 4)` .npy of LiDAR poses (e.g. from a scan registration).

    .venv/bin/python bench/pseudo_tracks.py --target RUN/data/drive_labels --pseudo RUN/iter1/pseudo \
        --drive DRIVE_DIR [--poses POSES.npy] [--out bench/results/pseudo_tracks.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from pseudo_labels import in_grid, match  # noqa: E402

from dali_cli.geometry import wrap_angle  # noqa: E402
from dali_cli.labels import tracks  # noqa: E402
from dali_cli.runtime.machine import cpu_model  # noqa: E402
from dali_cli.store.artifacts import FrameSet, read_boxes  # noqa: E402

CUTS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)


def drive_poses(drive_dir: Path, frame_ids: list[str]) -> np.ndarray:
    """`(n, 4, 4)` LiDAR poses of a raw drive's scans from its OXTS records."""
    from dali_cli.importers.kitti_raw import read_imu_to_velo
    from dali_cli.importers.oxts import drive_lidar_poses

    imu_to_velo = read_imu_to_velo(drive_dir.resolve().parent / "calib_imu_to_velo.txt")
    return drive_lidar_poses(drive_dir / "oxts" / "data", imu_to_velo, frame_ids)


def score_frames(frame_ids, frame, boxes, scores, truth_by_frame, iou):
    """Per box: matched (bool) and its truth box (nan when none); the truth's hit flags."""
    hit = np.zeros(len(boxes), bool)
    matched_truth = np.full((len(boxes), 7), np.nan)
    truth_hit = []
    for f, frame_id in enumerate(frame_ids):
        rows = np.flatnonzero(frame == f)
        t = truth_by_frame[frame_id]
        m = match(boxes[rows], scores[rows], t, iou)
        hit[rows] = m >= 0
        matched_truth[rows[m >= 0]] = t[m[m >= 0]]
        flags = np.zeros(len(t), bool)
        flags[m[m >= 0]] = True
        truth_hit.append(flags)
    return hit, matched_truth, np.concatenate(truth_hit)


def tightness(boxes: np.ndarray, truth: np.ndarray) -> dict:
    """Median |error| of matched pairs: centre along the range, length, yaw modulo pi."""
    if not len(boxes):
        return {}
    radial = truth[:, :2] / np.linalg.norm(truth[:, :2], axis=1, keepdims=True)
    along = np.einsum("ij,ij->i", boxes[:, :2] - truth[:, :2], radial)
    yaw = np.abs(wrap_angle(2 * (boxes[:, 6] - truth[:, 6]))) / 2
    return {
        "pairs": len(boxes),
        "range_m_median_abs": round(float(np.median(np.abs(along))), 3),
        "range_m_mean": round(float(along.mean()), 3),
        "length_m_median_abs": round(float(np.median(np.abs(boxes[:, 3] - truth[:, 3]))), 3),
        "length_m_mean": round(float((boxes[:, 3] - truth[:, 3]).mean()), 3),
        "yaw_deg_median_abs": round(float(np.degrees(np.median(yaw))), 2),
    }


def curve(frame_ids, frame, boxes, scores, cut_by, truth_by_frame, truth_total, iou, cuts):
    """Precision / recall and the true positives' tightness at every cut of `cut_by` `(N,)`;
    box counts only when `truth_by_frame` is None (an unlabelled sequence)."""
    rows, tight = [], None
    for cut in cuts:
        keep = (cut_by >= cut) & in_grid(boxes)
        if truth_by_frame is None:
            rows.append({"cut": cut, "boxes": int(keep.sum()), "precision": None, "recall": None})
            continue
        hit, matched, truth_hit = score_frames(
            frame_ids, frame[keep], boxes[keep], scores[keep], truth_by_frame, iou
        )
        rows.append(
            {
                "cut": cut,
                "boxes": int(keep.sum()),
                "true_positives": int(hit.sum()),
                "precision": round(float(hit.mean()), 4) if keep.any() else None,
                "recall": round(float(truth_hit.sum() / truth_total), 4),
                "tightness": tightness(boxes[keep][hit], matched[hit]),
            }
        )
        tight = tight or rows[-1]["tightness"]
    return {"curve": rows, "tightness_lowest_cut": tight}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--target", type=Path, required=True, help="drive FrameSet with labels")
    parser.add_argument("--pseudo", type=Path, required=True, help="pseudo-label directory")
    parser.add_argument("--drive", type=Path, help="raw drive directory (oxts/data)")
    parser.add_argument("--poses", type=Path, help="(n, 4, 4) .npy LiDAR poses instead")
    parser.add_argument("--iou", type=float, default=0.5)
    parser.add_argument("--min-points", type=int, default=5)
    parser.add_argument("--hits", type=int, nargs="+", default=[3])
    parser.add_argument("--gate-m", type=float, default=tracks.TrackParams.gate_m)
    parser.add_argument("--max-gap", type=int, default=tracks.TrackParams.max_gap)
    parser.add_argument("--min-hits", type=int, default=tracks.TrackParams.min_hits)
    parser.add_argument(
        "--place-points", type=int, nargs="+", default=[tracks.TrackParams.min_points]
    )
    parser.add_argument("--cuts", type=float, nargs="+", default=list(CUTS))
    parser.add_argument("--out", type=Path, default=ROOT / "bench/results/pseudo_tracks.json")
    args = parser.parse_args()

    frames_points = FrameSet(args.target)
    frame_ids = list(frames_points.frame_ids)
    truth_by_frame, truth_total = None, None
    if (args.target / "boxes.parquet").is_file():
        truth = read_boxes(args.target)
        truth = truth.select(np.asarray(truth["label"]).astype(str) == "Car")
        truth = truth.select(in_grid(truth.boxes) & (truth["num_points"] >= args.min_points))
        truth_rows = truth.rows_by_frame()
        truth_by_frame = {
            f: truth.boxes[truth_rows[f]] if f in truth_rows else np.zeros((0, 7))
            for f in frame_ids
        }
        truth_total = len(truth)

    pseudo = read_boxes(args.pseudo)
    position = {frame_id: i for i, frame_id in enumerate(frame_ids)}
    frame = np.array([position[f] for f in pseudo.frame_id], np.int64)
    boxes, scores = pseudo.boxes.astype(np.float64), np.asarray(pseudo["score"], np.float64)
    poses = np.load(args.poses) if args.poses else drive_poses(args.drive, frame_ids)
    params = tracks.TrackParams(gate_m=args.gate_m, max_gap=args.max_gap, min_hits=args.min_hits)
    world = np.empty_like(boxes)
    for f in range(len(frame_ids)):
        rows = frame == f
        world[rows] = tracks.boxes_to_world(boxes[rows], poses[f])
    track = tracks.link_tracks(frame, world, scores, params)
    hits = tracks.track_lengths(track)
    mean_score = tracks.track_mean(track, scores)

    def local(world_boxes, frames):
        out = np.empty_like(world_boxes)
        for f in np.unique(frames):
            rows = frames == f
            out[rows] = tracks.boxes_from_world(world_boxes[rows], poses[f])
        return out

    common = (frame_ids,)
    variants = {"raw": curve(*common, frame, boxes, scores, scores, truth_by_frame, truth_total,
                             args.iou, args.cuts)}  # fmt: skip
    for n in args.hits:
        keep = hits >= n
        f, b, s, m = frame[keep], boxes[keep], scores[keep], mean_score[keep]
        variants[f"persist-{n}"] = curve(
            *common, f, b, s, s, truth_by_frame, truth_total, args.iou, args.cuts
        )
        variants[f"track-{n}"] = curve(
            *common, f, b, s, m, truth_by_frame, truth_total, args.iou, args.cuts
        )
        sized = local(
            tracks.refine_tracks(track[keep], f, world[keep], static=False, params=params), f
        )
        variants[f"track-{n} + size"] = curve(
            *common, f, sized, s, m, truth_by_frame, truth_total, args.iou, args.cuts
        )
        refined_world = tracks.refine_tracks(track[keep], f, world[keep], params=params)
        refined = local(refined_world, f)
        variants[f"track-{n} + size + static"] = curve(
            *common, f, refined, s, m, truth_by_frame, truth_total, args.iou, args.cuts
        )
        gap_track, gap_frame, gap_world = tracks.fill_gaps(track[keep], f, refined_world)
        gap_score = np.array([m[track[keep] == t][0] for t in gap_track])
        filled_frame = np.concatenate([f, gap_frame])
        filled = np.concatenate([refined, local(gap_world, gap_frame)])
        filled_mean = np.concatenate([m, gap_score])
        variants[f"track-{n} + size + static + fill"] = curve(
            *common, filled_frame, filled, filled_mean, filled_mean, truth_by_frame,
            truth_total, args.iou, args.cuts,
        )  # fmt: skip
    frames_points_of = lambda f: frames_points.frame(frame_ids[f])  # noqa: E731
    for min_points in args.place_points:
        tracked = tracks.track_boxes(
            frame, boxes, scores, np.asarray(pseudo["num_points"]), poses, frames_points_of,
            replace(params, min_points=min_points),
        )  # fmt: skip
        variants[f"parked (>= {min_points} points)"] = curve(
            *common, tracked.frame, tracked.boxes, tracked.score, tracked.score, truth_by_frame,
            truth_total, args.iou, args.cuts,
        )  # fmt: skip
    lengths = np.bincount(np.unique(track, return_inverse=True)[1])
    result = {
        "command": "bench/pseudo_tracks.py " + " ".join(sys.argv[1:]),
        "machine": {"cpu_model": cpu_model(), "load_1min": round(os.getloadavg()[0], 2)},
        "truth_cars": truth_total,
        "pseudo_boxes": len(pseudo),
        "tracks": int(len(lengths)),
        "parked_cars": int(len(np.unique(tracked.car[tracked.parked]))),
        "moving_tracks": int(len(np.unique(tracked.car[~tracked.parked]))),
        "track_hits_histogram": np.bincount(lengths).tolist(),
        "params": {**vars(params), "iou": args.iou},
        "variants": variants,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    for name, variant in variants.items():
        cells = "  ".join(
            f"{row['cut']:.2f}:{row['precision'] or 0:.2f}/{row['recall'] or 0:.2f}/{row['boxes']}"
            for row in variant["curve"]
        )
        print(f"{name:34s} {cells}")
    for name, variant in variants.items():
        for row in variant["curve"]:
            if row["cut"] in (min(args.cuts), 0.5):
                print(f"{name:34s} {row['cut']:.2f} {row.get('tightness')}")
    print({key: result[key] for key in ("tracks", "parked_cars", "moving_tracks")})


if __name__ == "__main__":
    main()
