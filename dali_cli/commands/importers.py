"""`dali import kitti|kitti-raw|kitti-odometry|nuscenes|openpcdet|waymo`: other datasets' files -> a FrameSet + boxes.parquet."""

from __future__ import annotations

from pathlib import Path

import click

from dali_cli.commands import common
from dali_cli.commands.kinds import INTENSITY_MAX, VIEW_DEG


@click.group(name="import")
def command() -> None:
    """Import real data as a dali frame set (frames.zarr) with boxes (boxes.parquet).

    Points end up in the dali sensor frame (x forward, y left, z up, intensity in [0, 1]); boxes
    are LiDAR-frame geometric centres (x, y, z, l, w, h, yaw). Each import is a stage: the output
    is written atomically with a manifest.json and skipped when up to date.
    """


def _summary(outcome) -> None:
    if (counts := common.ran_counts(outcome)) is not None:
        by_label = ", ".join(f"{k} {v}" for k, v in counts.get("boxes_by_label", {}).items())
        click.echo(
            f"  {counts['frames']} frames, {counts['points']} points, "
            f"{counts.get('boxes', 0)} boxes{f' ({by_label})' if by_label else ''}, "
            f"{counts['frames_without_labels']} frames without labels"
        )


# ---------------------------------------------------------------------------------------------


@command.command(name="kitti", short_help="KITTI velodyne + label_2 + calib.")
@click.argument("root", type=click.Path(exists=True, file_okay=False))
@common.choice_option("--split", choices=["training", "testing"], default="training",
                      help="Split directory under ROOT (ignored when ROOT itself holds velodyne/).")  # fmt: skip
@click.option("--ids", "ids_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Text file of frame ids, one per line (e.g. ImageSets/val.txt). Default: "
                   "every scan.")  # fmt: skip
@click.option("--label-dir", type=click.Path(exists=True, file_okay=False), default=None,
              help="Read labels from here instead of <split>/label_2 (e.g. exported predictions).")  # fmt: skip
@click.option("--crop-fov", is_flag=True,
              help="Keep only points that project into the camera image (KITTI labels cover only "
                   "it).")  # fmt: skip
@click.option("--intensity-max", type=INTENSITY_MAX, default=1.0, show_default=True,
              help="Reflectances are divided by this (255 for 8-bit ones); after it they must lie "
                   "in [0, 1].")  # fmt: skip
@common.beams_options
@common.import_options("kitti")
def kitti_command(
    root, split, ids_path, label_dir, crop_fov, intensity_max, sensor, out, no_progress, **run
):
    """Import KITTI object data from ROOT (holding training/ and testing/, or one split).

    Reads <split>/velodyne/*.bin (float32 x, y, z, reflectance), label_2/*.txt (camera frame,
    h w l, bottom centre, rotation_y; 15 fields, or 16 with a score) and calib/*.txt (P2,
    R0_rect, Tr_velo_to_cam). Writes OUT/frames.zarr and, when any frame has labels,
    OUT/boxes.parquet: LiDAR-frame boxes through the calib, with label (the KITTI type, DontCare
    and Van kept as rows for the evaluation to ignore), truncated, occluded, alpha, the 2D bbox
    and the in-box point count. Frames without a label file are allowed (an unlabelled target);
    a frame with labels needs its calib file.
    """
    from stages.import_kitti import import_kitti

    outcome = import_kitti(
        root, out, split=split, ids_path=ids_path, label_dir=label_dir, crop_fov=crop_fov,
        sensor=sensor, intensity_max=intensity_max, progress=not no_progress, **run,
    )  # fmt: skip
    _summary(outcome)


# ---------------------------------------------------------------------------------------------


@command.command(name="kitti-raw", short_help="KITTI raw synced drive + tracklet_labels.xml.")
@click.argument("drive_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--calib-dir", type=click.Path(exists=True, file_okay=False), default=None,
              help="Folder of calib_cam_to_cam.txt and calib_velo_to_cam.txt. Default: "
                   "DRIVE_DIR/.. (the date folder).")  # fmt: skip
@click.option("--tracklets", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Tracklet file. Default: DRIVE_DIR/tracklet_labels.xml when present.")  # fmt: skip
@click.option("--no-labels", is_flag=True,
              help="Import the scans only, without boxes (an unlabelled target).")  # fmt: skip
@click.option("--crop-fov", is_flag=True,
              help="Keep only points that project into the left colour camera's image.")  # fmt: skip
@click.option("--poses", is_flag=True,
              help="Also keep each scan's LiDAR pose (from DRIVE_DIR/oxts/data and the calib "
                   "folder's calib_imu_to_velo.txt) as OUT/sequence.parquet, for "
                   "`dali track-pseudo`.")  # fmt: skip
@common.beams_options
@common.import_options("kitti")
def kitti_raw_command(
    drive_dir, calib_dir, tracklets, no_labels, crop_fov, poses, sensor, out, no_progress, **run
):
    """Import a KITTI raw synced drive DRIVE_DIR (YYYY_MM_DD_drive_NNNN_sync).

    Reads velodyne_points/data/*.bin (float32 x, y, z, reflectance; frame ids are the file
    names' frame indices), the date folder's calib_cam_to_cam.txt (R_rect_00, P_rect_02,
    S_rect_02) and calib_velo_to_cam.txt (R, T), and tracklet_labels.xml when present: each
    tracklet pose (Velodyne frame, bottom centre, rz) on a frame of the drive becomes a box
    (label = objectType) with KITTI's label columns (2D box projected through P_rect_02 and
    R_rect_00, truncation, occlusion, alpha) and its in-box point count. Writes OUT/frames.zarr
    and OUT/boxes.parquet; with --poses also OUT/sequence.parquet (frame_id, index and
    lidar_pose_00..lidar_pose_23: each scan's 3 x 4 LiDAR pose in the first scan's LiDAR frame,
    from its OXTS record by the raw devkit's convertOxtsToPose).
    """
    from stages.import_kitti_raw import import_kitti_raw

    outcome = import_kitti_raw(
        drive_dir, out, calib_dir=calib_dir, tracklets=tracklets, labels=not no_labels,
        crop_fov=crop_fov, sensor=sensor, progress=not no_progress, poses=poses, **run,
    )  # fmt: skip
    _summary(outcome)


@command.command(name="kitti-odometry", short_help="KITTI odometry / SemanticKITTI sequence.")
@click.argument("sequence_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--calib", type=click.Path(exists=True, dir_okay=False), default=None,
              help="calib.txt (P2, Tr). Default: SEQUENCE_DIR/calib.txt when present.")  # fmt: skip
@click.option("--poses", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Poses file (3 x 4 per line). Default: SEQUENCE_DIR/poses.txt, else "
                   "SEQUENCE_DIR/../../poses/<NN>.txt (the devkit layout), when present.")  # fmt: skip
@click.option("--crop-fov", is_flag=True,
              help="Keep only points that project into camera 2's image (needs the calib).")  # fmt: skip
@common.tuning_option("--crop-front-deg", type=VIEW_DEG, default=None,
                     metavar="DEG",
                     help="Keep only points within ±DEG/2 of straight ahead in azimuth (for a sequence "
                          "without calib; KITTI's camera 2 sees about 82 degrees).")  # fmt: skip
@common.beams_options
@common.import_options("kitti")
def kitti_odometry_command(
    sequence_dir, calib, poses, crop_fov, crop_front_deg, sensor, out, no_progress, **run
):
    """Import a KITTI odometry or SemanticKITTI sequence SEQUENCE_DIR (sequences/NN), unlabeled.

    Reads velodyne/*.bin (float32 x, y, z, reflectance; frame ids are the file names' scan
    indices), calib.txt (P2 and Tr: velodyne -> rectified camera 0) when present, times.txt and
    the poses (3 x 4 camera-0 poses, one a line) when present. Line i of times.txt and of the
    poses belongs to scan i, so a directory with part of a sequence's scans reads their lines.
    Writes OUT/frames.zarr and, with times or poses, OUT/sequence.parquet (frame_id, index,
    time_s, camera_pose_00 .. camera_pose_23: the poses as given, row-major; with calib.txt also
    lidar_pose_00 .. lidar_pose_23 = inv(Tr) . pose . Tr, each scan's LiDAR pose in the LiDAR
    frame of scan 0 of the sequence, which `dali track-pseudo` needs).
    """
    from stages.import_kitti_odometry import import_kitti_odometry

    outcome = import_kitti_odometry(
        sequence_dir, out, calib=calib, poses=poses, crop_fov=crop_fov,
        crop_front_deg=crop_front_deg, sensor=sensor, progress=not no_progress, **run,
    )  # fmt: skip
    _summary(outcome)


@command.command(name="nuscenes", short_help="nuScenes LIDAR_TOP, JSON tables or LiDAR-frame CSV.")
@click.argument("path", type=click.Path(exists=True))
@click.option("--version", "version", default="v1.0-mini", show_default=True,
              help="Table directory under the data root (v1.0-trainval, v1.0-mini, ...).")  # fmt: skip
@click.option("--boxes-csv", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Boxes already in the LiDAR frame (columns "
                   "category,x,y,z,l,w,h,yaw[,num_lidar_pts][,frame_id]); PATH is then a "
                   ".pcd.bin file or a directory of them.")  # fmt: skip
@click.option("--car-category", "car_categories", multiple=True,
              help="Category mapped to label 'Car' (repeatable). Default: vehicle.car and car. "
                   "Other categories keep their name as label.")  # fmt: skip
@click.option("--scenes", default=None,
              help="Comma-separated scene names to import (JSON tables only). Default: all key "
                   "frames.")  # fmt: skip
@click.option("--max-frames", type=click.IntRange(min=1), default=None,
              help="Import only the first N key frames (in time order per scene).")  # fmt: skip
@common.tuning_option("--lidar-frame", is_flag=True,
                     help="Keep nuScenes' LiDAR axes (x right, y forward) instead of turning them to "
                          "dali's x forward, y left.")  # fmt: skip
@common.import_options("nuscenes")
def nuscenes_command(
    path,
    version,
    boxes_csv,
    car_categories,
    scenes,
    max_frames,
    lidar_frame,
    sensor,
    out,
    no_progress,
    **run,
):
    """Import nuScenes LIDAR_TOP key frames.

    With the v1.0 JSON tables, PATH is the data root (holding samples/ and VERSION/): boxes come
    from sample_annotation (global frame, size w, l, h) through ego_pose and calibrated_sensor
    into the LiDAR frame; no devkit needed. With --boxes-csv, PATH is one .pcd.bin (or a
    directory of them) and the CSV gives LiDAR-frame boxes. Points are the .pcd.bin's float32
    x, y, z, intensity, ring (ring dropped, intensity / 255). Only key-frame sweeps are read (no
    multi-sweep accumulation). By default points and boxes are rotated by -90 degrees about z so
    that x points forward as in dali's convention; the rotation is recorded in the manifest.
    Writes OUT/frames.zarr and OUT/boxes.parquet (num_points = in-box point count; the dataset's
    num_lidar_pts kept as a column).
    """
    from stages.import_nuscenes import import_nuscenes

    outcome = import_nuscenes(
        path, out, version=version, boxes_csv=boxes_csv, scenes=scenes,
        car_categories=tuple(car_categories), max_frames=max_frames, lidar_frame=lidar_frame,
        sensor=sensor, progress=not no_progress, **run,
    )  # fmt: skip
    _summary(outcome)


# ---------------------------------------------------------------------------------------------


@command.command(
    name="openpcdet", short_help="OpenPCDet custom format (points/*.npy, labels/*.txt)."
)
@click.argument("root", type=click.Path(exists=True, file_okay=False))
@click.option("--split", default=None,
              help="Read ids from ROOT/ImageSets/SPLIT.txt (e.g. train, val). Default: every "
                   "points/*.npy.")  # fmt: skip
@click.option("--car-class", "car_classes", multiple=True,
              help="Class name mapped to label 'Car' (repeatable). Default: Car and Vehicle.")  # fmt: skip
@click.option("--intensity-max", type=INTENSITY_MAX, default=1.0,
              show_default=True,
              help="Intensities are divided by this (255 for 8-bit intensities).")  # fmt: skip
@common.import_options(None)
def openpcdet_command(root, split, car_classes, intensity_max, sensor, out, no_progress, **run):
    """Import OpenPCDet's custom format from ROOT.

    Reads ROOT/points/ID.npy ((n, 4) x, y, z, intensity; more columns are dropped) and
    ROOT/labels/ID.txt (one box a line: x y z dx dy dz heading class; LiDAR frame, geometric
    centre, dx along the heading). A frame without a label file has no labels. Writes
    OUT/frames.zarr and OUT/boxes.parquet.
    """
    from stages.import_openpcdet import import_openpcdet

    outcome = import_openpcdet(
        root, out, sensor=sensor, split=split, car_classes=tuple(car_classes),
        intensity_max=intensity_max, progress=not no_progress, **run,
    )  # fmt: skip
    _summary(outcome)


# ---------------------------------------------------------------------------------------------


@command.command(name="waymo", short_help="Waymo Open Dataset v2 Parquet or v1 TFRecord.")
@click.argument("root", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--format", "fmt", type=click.Choice(["auto", "v2", "v1"]), default="auto",
              show_default=True,
              help="auto: v2 when ROOT has lidar/*.parquet, v1 when it has *.tfrecord.")  # fmt: skip
@click.option("--split", default=None, help="Read ROOT/SPLIT (e.g. training, validation).")
@click.option("--every", type=click.IntRange(min=1), default=1, show_default=True,
              help="Keep every K-th frame of each segment (the paper trains on every 5th).")  # fmt: skip
@common.choice_option("--lidars", choices=["top", "all"], default="top",
                      help="Points of the TOP LiDAR only, or of all five.")  # fmt: skip
@click.option("--returns", type=click.IntRange(1, 2), default=1, show_default=True,
              help="First return only, or both returns.")  # fmt: skip
@click.option("--segments", default=None, help="Comma-separated segment names (default: all).")
@common.import_options("waymo")
def waymo_command(
    root, fmt, split, every, lidars, returns, segments, sensor, out, no_progress, **run
):
    """Import Waymo Open Dataset frames without TensorFlow.

    v2: ROOT[/SPLIT]/<component>/<segment>.parquet with the components lidar,
    lidar_calibration and (optional) lidar_box, vehicle_pose, lidar_pose; only the needed
    columns are read, the lidar component one row group at a time. v1: ROOT[/SPLIT]/*.tfrecord
    (Frame protobufs; CRCs checked). Range images become points in the TOP LiDAR's frame
    (x forward, y left, z up, origin at the sensor), with the TOP's per-pixel (rolling-shutter)
    pose applied when present, returns with range <= 0 dropped and intensity mapped by tanh to
    [0, 1). Boxes: Car for TYPE_VEHICLE, Pedestrian, Sign, Cyclist, DontCare for the others;
    num_points = the dataset's num_lidar_points_in_box. Frame ids: <segment>_<timestamp>.
    The manifest records per-segment counts and the TOP calibration (beam elevations, mount
    height) for a sensor profile.
    """
    from stages.import_waymo import import_waymo

    outcome = import_waymo(
        root, out, fmt=fmt, split=split, every=every, lidars=lidars, returns=returns,
        segments=segments, sensor=sensor, progress=not no_progress, **run,
    )  # fmt: skip
    _summary(outcome)
