"""Stage detect: a trained model's boxes on a user's own scans (`dali detect`).

Reads SCANS (dali_cli.importers.scans: scan files, a folder of them, a KITTI raw drive or object
split, or a dali frame set), runs the detector at the model's test-time scale (its scale.json, or
--scale / --scale-from) and writes OUT/boxes.parquet (LiDAR frame, score, num_points), one
KITTI label_2 file a scan under OUT/label_2 (camera frame, with calibration) or a LiDAR-frame text
table OUT/lidar/<frame>.txt (without), and the manifest. Its boxes are the model's own, those
`dali eval` scores: pseudo-label's size correction and point fit are not applied.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.importers.calibration import frame_calib, load_calib
from dali_cli.runtime import console
from dali_cli.runtime.errors import StageError
from dali_cli.store.manifest import StageOutcome, run_stage

FULL_SCAN_BEHIND_SHARE = 0.1  # a scan with this share of its points behind the sensor is 360°
LIDAR_TABLE_FIELDS = "x y z l w h yaw Car score"  # OUT/lidar/<frame>.txt, OpenPCDet's order + score


@dataclass(frozen=True)
class Source:
    """What detect reads: (frame id, points (n, 4) sensor frame) pairs, their count, the sensor
    profile whose mount height sets the ground (None: the model's) and the calibration (one
    kitti.Calibration for every scan, a directory of <frame>.txt, or None)."""

    frames: object  # callable () -> iterator of (frame_id, points)
    count: int
    sensor: str | None
    calib: object
    described: str


def scans_source(scans: Path, sensor: str | None, calib: Path | None) -> Source:
    """The scans of SCANS with their sensor (given, else by format) and calibration (given, else
    a KITTI raw drive's date folder or an object split's calib/ when there)."""
    from dali_cli.importers.scans import find_scans, read_scan
    from dali_cli.store.artifacts import FRAMES_NAME, FrameSet

    if (scans / FRAMES_NAME).is_dir():
        frames = FrameSet(scans)
        return Source(frames.iter_frames, len(frames), sensor or frames.sensor,
                      load_calib(calib), "a dali frame set")  # fmt: skip
    found = find_scans(scans)
    kinds = sorted({scan.kind for scan in found})
    if sensor is None and kinds in (["kitti-bin"], ["nuscenes-bin"]):
        sensor = "kitti" if kinds == ["kitti-bin"] else "nuscenes"
    if calib is None and scans.is_dir():
        if (scans / "velodyne_points").is_dir() and (
            scans.parent / "calib_cam_to_cam.txt"
        ).is_file():
            calib = scans.parent  # a KITTI raw drive: the day's calib files
        elif (scans / "calib").is_dir() and (scans / "velodyne").is_dir():
            calib = scans / "calib"  # a KITTI object split
    return Source(lambda: ((scan.frame_id, read_scan(scan)) for scan in found), len(found),
                  sensor, load_calib(calib), f"{len(found)} {'/'.join(kinds)} scans")  # fmt: skip


def crop_front(points: np.ndarray, front_deg: float | None) -> np.ndarray:
    """The points `(n, 4)` within `front_deg` degrees of azimuth about +x (all for None)."""
    if front_deg is None:
        return points
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    return points[np.abs(azimuth) <= front_deg / 2]


def lidar_lines(boxes: np.ndarray, scores: np.ndarray) -> str:
    """OUT/lidar/<frame>.txt: a line a box, x y z l w h yaw (m, rad, LiDAR frame) Car score."""
    return "".join(
        " ".join(f"{v:.4f}" for v in box) + f" Car {score:.4f}\n"
        for box, score in zip(boxes, scores, strict=True)
    )


def build_detect(tmp: Path, detector, source: Source, scale: float, mount, score_min: float,
                 front_deg, batch_size: int, progress: bool, fusion=None) -> dict:  # fmt: skip
    """Write boxes.parquet and the per-scan text files into `tmp`; returns the counts. `fusion`:
    a detector.fusion.TestTimeFusion (several passes, fused) or None."""
    from tqdm import tqdm

    from dali_cli.export import frame_label_lines
    from dali_cli.geometry import count_points_in_boxes
    from dali_cli.store.artifacts import BoxTable, write_boxes
    from dali_cli.store.frame_ids import check_name, child_path

    text_dir = tmp / ("label_2" if source.calib is not None else "lidar")
    text_dir.mkdir()
    tables, full_scans, started = [], 0, time.perf_counter()
    bar = tqdm(total=source.count, desc="detect", unit="frame", disable=not progress, leave=False)
    batch: list[tuple[str, np.ndarray]] = []

    def flush():
        nonlocal full_scans
        clouds = [points for _, points in batch]
        if fusion is not None:
            found = fusion.predict(detector, clouds, scale, mount, batch_size)
        else:
            found = detector.predict(clouds, scale, mount, batch_size)
        for (frame_id, points), (boxes, scores) in zip(batch, found, strict=True):
            keep = scores >= score_min
            boxes, scores = boxes[keep], scores[keep]
            counts = count_points_in_boxes(points, boxes) if len(boxes) else np.zeros(0, np.int64)
            table = BoxTable.from_arrays([frame_id] * len(boxes), boxes, score=scores,
                                         label="Car", num_points=counts)  # fmt: skip
            tables.append(table)
            path = child_path(text_dir, frame_id, ".txt")
            if source.calib is not None:
                lines = frame_label_lines(table, frame_calib(source.calib, frame_id)).lines
                path.write_text("".join(line + "\n" for line in lines))
            else:
                path.write_text(lidar_lines(boxes, scores))
            bar.update(1)
        batch.clear()

    for frame_id, points in source.frames():
        check_name(frame_id, "detect: scan", "frame id")
        if np.mean(points[:, 0] < 0) > FULL_SCAN_BEHIND_SHARE and front_deg is None:
            full_scans += 1
        batch.append((frame_id, crop_front(points, front_deg)))
        if len(batch) == batch_size:
            flush()
    if batch:
        flush()
    bar.close()
    seconds = time.perf_counter() - started
    table = BoxTable.concat(tables) if tables else BoxTable.empty()
    write_boxes(tmp, table)
    return {"frames": source.count, "boxes": len(table), "full_360_scans": full_scans,
            "seconds": round(seconds, 2),
            "frames_per_s": round(source.count / seconds, 3) if seconds > 0 else None}  # fmt: skip


def run_detect(*, model: str | Path, scans: str | Path, out: str | Path, scale=None,
               scale_from=None, sensor: str | None = None, calib=None, score_min: float = 0.3,
               front_deg: float | None = None, batch_size: int = 4, device: str = "auto",
               precision: str = "fp32", progress: bool = True, force: bool = False,
               dry_run: bool = False, sensors_path=None, rerun=None,
               tta=None) -> StageOutcome:  # fmt: skip
    """Run the stage (see the module docstring); `rerun`: also write a Rerun recording of the
    scans and their boxes there (reporting/recording.py); `tta`: test-time fusion's (flip, scale
    factors, IoU) (dali_cli.detector.fusion)."""
    from dali_cli.detector.fusion import fusion_of
    from dali_cli.detector.infer import WEIGHTS_NAME, Detector
    from dali_cli.runtime.device import resolve_device
    from dali_cli.sensors import get_profile
    from dali_cli.store.scale_file import model_scale

    model, scans = Path(model), Path(scans)
    if not (model / WEIGHTS_NAME).is_file():
        raise StageError(f"{model}: no {WEIGHTS_NAME} here: not a dali model directory")
    scale = model_scale(model, scale, scale_from)
    source = scans_source(scans, sensor, Path(calib) if calib is not None else None)
    mount = get_profile(source.sensor, sensors_path).mount_height_m if source.sensor else None
    torch_device = resolve_device(device)
    params = {"scale": scale, "sensor": source.sensor, "score_min": score_min,
              "front_deg": front_deg, "scans": source.count}  # fmt: skip
    fusion = fusion_of(tta)
    if fusion is not None:  # absent without: older artifacts stay up to date
        params["test_time_fusion"] = fusion.record()

    def build(tmp: Path) -> dict:
        detector = Detector.load(model, device=torch_device, precision=precision)
        passes = f", {len(fusion.passes)} passes fused" if fusion is not None else ""
        console.echo(
            f"detect: {source.described} ({source.sensor or 'the model mount height'}), scale "
            f"{scale:.4f}{passes}, on {torch_device}"
        )
        counts = build_detect(tmp, detector, source, scale, mount, score_min, front_deg,
                              batch_size, progress, fusion)  # fmt: skip
        if counts["full_360_scans"]:
            console.echo(
                f"detect: {counts['full_360_scans']} of {source.count} scans cover the full "
                "360°; a model trained on camera-view crops (models/kitti-hdl64e: its card) is "
                "less reliable off the front: --front-deg 82 crops to KITTI's camera view"
            )
        return counts

    inputs = {"model": model, "scans": scans, "calib": calib}
    if rerun is not None:  # before any work: a path dali must not write fails at once
        from dali_cli.store.output_paths import check_file_output, is_dali_recording

        check_file_output(rerun, {**inputs, "out": out}, is_dali_recording,
                          "a recording dali wrote", option="--rerun")  # fmt: skip
    outcome = run_stage("detect", out, inputs, params, build, force=force, dry_run=dry_run)
    if rerun is not None and not dry_run:
        from dali_cli.reporting.recording import Layer, write_recording
        from dali_cli.store.artifacts import read_boxes

        frames = ((i, crop_front(p, front_deg)) for i, p in source.frames())
        counts = write_recording(Path(rerun), frames, [Layer("detections", read_boxes(out))])
        console.echo(f"detect: wrote {rerun} ({counts['frames']} frames); open it: rerun {rerun}")
    return outcome
