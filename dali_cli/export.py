"""Export dali box tables as KITTI label_2 files, so the KITTI devkit or OpenPCDet can score them.

Each LiDAR-frame box goes to the rectified camera through the frame's calib (inverse of the
importer's conversion), its 2D box is the projection of its 8 corners clipped to the image, and
alpha is rotation_y minus the viewing angle. Output: `OUT/data/<frame>.txt`, one file per frame
(an empty file for a frame without boxes), the layout of the devkit's results directory.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.importers import kitti_label
from dali_cli.importers.common import ImportFormatError
from dali_cli.importers.kitti import (
    DEFAULT_IMAGE_SIZE,
    IGNORE_TYPES,
    Calibration,
    image_boxes,
    lidar_boxes_to_camera,
    observation_angle,
    png_size,
    read_calib,
)
from dali_cli.store.artifacts import BoxTable
from dali_cli.store.frame_ids import child_path

LABEL_DECIMALS = 4  # KITTI's own files have 2; 4 keep export -> import within 1e-4 m
KITTI_COLUMNS = (
    "truncated",
    "occluded",
    "alpha",
    "bbox_left",
    "bbox_top",
    "bbox_right",
    "bbox_bottom",
)


@dataclass
class FrameExport:
    """The label lines of one frame and how many boxes were left out (outside the image)."""

    lines: list[str]
    outside: int


def frame_label_lines(
    table: BoxTable,
    calib: Calibration,
    image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE,
    keep_outside: bool = False,
    reuse_columns: bool = True,
    with_score: bool = True,
) -> FrameExport:
    """label_2 lines for the boxes of one frame (LiDAR frame, through `calib`).

    reuse_columns: when the table has the KITTI columns (an imported label set), write its
    truncated, occluded, alpha and 2D box as they are, DontCare rows included; otherwise compute
    alpha and the 2D box, write -1 for truncation and occlusion (as OpenPCDet does for
    predictions) and leave DontCare rows out.
    keep_outside: also write boxes behind the camera or outside the image (their 2D box is empty).
    """
    reuse = reuse_columns and all(name in table.columns for name in KITTI_COLUMNS)
    ignore = np.isin(table["label"].astype(str), IGNORE_TYPES)
    if not reuse:
        table, ignore = table.select(~ignore), ignore[~ignore]
    location, hwl, rotation_y = lidar_boxes_to_camera(table.boxes, calib)
    bbox, visible = image_boxes(location, hwl, rotation_y, calib, image_size)
    count = len(table)
    if reuse:
        columns = {name: table[name] for name in KITTI_COLUMNS}
    else:
        columns = {
            "truncated": np.full(count, -1.0, np.float32),
            "occluded": np.full(count, -1, np.int32),
            "alpha": observation_angle(location, rotation_y),
            **{name: bbox[:, k] for k, name in enumerate(KITTI_COLUMNS[3:])},
        }
    keep = np.ones(count, bool) if keep_outside else visible | ignore
    rows = np.flatnonzero(keep)
    # kitti_label writes label_2 lines from its calib-free pseudo-LiDAR frame: hand it the
    # calib-correct camera boxes in that frame
    camera = BoxTable.from_arrays(
        table.frame_id[rows],
        kitti_label.camera_to_pseudo_lidar(hwl[rows], location[rows], rotation_y[rows]),
        score=table["score"][rows],
        label=table["label"][rows],
        **{name: np.asarray(values)[rows] for name, values in columns.items()},
    )
    lines = kitti_label.format_label_lines(camera, with_score=with_score, decimals=LABEL_DECIMALS)
    return FrameExport(lines, int(count - len(rows)))


def build_export_kitti(
    out: str | Path,
    table: BoxTable,
    frame_ids: list[str],
    calib_dir: Path,
    image_dir: Path | None = None,
    image_size: tuple[int, int] | None = None,
    keep_outside: bool = False,
    reuse_columns: bool = True,
    with_score: bool = True,
    progress: bool = True,
) -> dict:
    """Stage body of `dali export kitti`: write OUT/data/<frame>.txt for every frame id
    (`progress`: a progress bar on stderr).

    The image size comes from `image_size`, else the frame's image_2 PNG, else 1242 x 375.
    A frame without its calib file is an error naming the file.
    """
    from tqdm import tqdm

    data = Path(out) / "data"
    data.mkdir(parents=True)
    for frame_id in frame_ids:  # refuse before writing anything (and before reading calib files)
        child_path(data, frame_id, ".txt")
    rows = table.rows_by_frame()
    written = outside = 0
    for frame_id in tqdm(
        frame_ids, desc="export kitti", unit="frame", disable=not progress, leave=False
    ):
        calib_path = calib_dir / f"{frame_id}.txt"
        if not calib_path.is_file():
            raise ImportFormatError(f"{calib_path}: calib file missing for frame '{frame_id}'")
        size = image_size
        if size is None and image_dir is not None:
            size = png_size(image_dir / f"{frame_id}.png")
        frame = table.select(rows.get(frame_id, np.zeros(0, np.int64)))
        result = frame_label_lines(
            frame,
            read_calib(calib_path),
            size or DEFAULT_IMAGE_SIZE,
            keep_outside,
            reuse_columns,
            with_score,
        )
        # child_path: refuses a file outside OUT/data whatever the id (ids are also checked
        # where they entered dali)
        path = child_path(data, frame_id, ".txt")
        path.write_text("".join(line + "\n" for line in result.lines))
        written += len(result.lines)
        outside += result.outside
    return {"frames": len(frame_ids), "boxes_written": written, "boxes_outside_image": outside}
