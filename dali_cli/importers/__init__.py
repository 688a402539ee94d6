"""Readers that turn other datasets' files into dali artifacts (FrameSet + box table).

One module per format: `kitti` (velodyne, label_2, calib), `nuscenes` (LIDAR_TOP `.pcd.bin` and the
v1.0 JSON tables or a LiDAR-frame CSV), `openpcdet` (the custom `points/*.npy` + `labels/*.txt`
layout). Every reader validates what it reads and raises `ImportFormatError` naming the file, the
line (or point) and the field.
"""

from dali_cli.importers.common import ImportFormatError, read_float_records

__all__ = ["ImportFormatError", "read_float_records"]
