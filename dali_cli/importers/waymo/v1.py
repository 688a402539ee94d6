"""Waymo Open Dataset v1: `segment-*.tfrecord` files of `Frame` protobufs, read without
TensorFlow: TFRecord framing with masked CRC-32C checks, the `protobuf` runtime with the few
messages dali needs declared here (field numbers from the dataset's dataset.proto and
label.proto; unknown fields, e.g. camera images, are skipped by the parser), zlib-compressed
`MatrixFloat` range images.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import numpy as np

from dali_cli.importers.waymo.frame import (
    LaserCalibration,
    LaserScan,
    WaymoFormatError,
    WaymoFrame,
)

_MASK_DELTA = 0xA282EAD8

# message → [(field, number, type, repeated, message type)]; types as in descriptor_pb2
_DOUBLE, _FLOAT, _INT64, _INT32, _STRING, _MESSAGE, _BYTES, _ENUM = 1, 2, 3, 5, 9, 11, 12, 14
MESSAGES = {
    "MatrixShape": [("dims", 1, _INT32, True, None)],
    "MatrixFloat": [("data", 1, _FLOAT, True, None), ("shape", 2, _MESSAGE, False, "MatrixShape")],
    "Transform": [("transform", 1, _DOUBLE, True, None)],
    "LaserCalibration": [
        ("name", 1, _INT32, False, None),
        ("beam_inclinations", 2, _DOUBLE, True, None),
        ("beam_inclination_min", 3, _DOUBLE, False, None),
        ("beam_inclination_max", 4, _DOUBLE, False, None),
        ("extrinsic", 5, _MESSAGE, False, "Transform"),
    ],
    "Context": [
        ("name", 1, _STRING, False, None),
        ("laser_calibrations", 3, _MESSAGE, True, "LaserCalibration"),
    ],
    "RangeImage": [
        ("range_image_compressed", 2, _BYTES, False, None),
        ("range_image_pose_compressed", 4, _BYTES, False, None),
    ],
    "Laser": [
        ("name", 1, _INT32, False, None),
        ("ri_return1", 2, _MESSAGE, False, "RangeImage"),
        ("ri_return2", 3, _MESSAGE, False, "RangeImage"),
    ],
    "Box": [
        ("center_x", 1, _DOUBLE, False, None),
        ("center_y", 2, _DOUBLE, False, None),
        ("center_z", 3, _DOUBLE, False, None),
        ("width", 4, _DOUBLE, False, None),
        ("length", 5, _DOUBLE, False, None),
        ("height", 6, _DOUBLE, False, None),
        ("heading", 7, _DOUBLE, False, None),
    ],
    "Label": [
        ("box", 1, _MESSAGE, False, "Box"),
        ("type", 3, _INT32, False, None),
        ("id", 4, _STRING, False, None),
        ("num_lidar_points_in_box", 7, _INT32, False, None),
    ],
    "Frame": [
        ("context", 1, _MESSAGE, False, "Context"),
        ("timestamp_micros", 2, _INT64, False, None),
        ("pose", 3, _MESSAGE, False, "Transform"),
        ("lasers", 5, _MESSAGE, True, "Laser"),
        ("laser_labels", 6, _MESSAGE, True, "Label"),
    ],
}  # enums are declared as int32: the same varint on the wire


@cache
def message_classes() -> dict[str, type]:
    """Protobuf message classes for MESSAGES (package `dali_waymo`), built at run time."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    proto = descriptor_pb2.FileDescriptorProto(name="dali_waymo.proto", package="dali_waymo")
    for name, fields in MESSAGES.items():
        message = proto.message_type.add(name=name)
        for field_name, number, kind, repeated, type_name in fields:
            entry = message.field.add(name=field_name, number=number, type=kind)
            entry.label = entry.LABEL_REPEATED if repeated else entry.LABEL_OPTIONAL
            if type_name:
                entry.type_name = f".dali_waymo.{type_name}"
            if repeated and kind in (_DOUBLE, _FLOAT, _INT32):
                entry.options.packed = True
    pool = descriptor_pool.DescriptorPool()
    pool.Add(proto)
    return {
        name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"dali_waymo.{name}"))
        for name in MESSAGES
    }


def masked_crc(data: bytes) -> int:
    """TFRecord's masked CRC-32C of `data`."""
    import google_crc32c

    crc = google_crc32c.value(data)
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


def read_records(path: Path) -> Iterator[bytes]:
    """The records of a TFRecord file, each length and payload CRC checked."""
    with open(path, "rb") as handle:
        index = 0
        while header := handle.read(12):
            if len(header) < 12:
                raise WaymoFormatError(f"{path}: record {index}: truncated header")
            length, length_crc = struct.unpack("<QI", header)
            if masked_crc(header[:8]) != length_crc:
                raise WaymoFormatError(f"{path}: record {index}: length CRC mismatch (corrupt)")
            payload = handle.read(length)
            footer = handle.read(4)
            if len(payload) < length or len(footer) < 4:
                raise WaymoFormatError(f"{path}: record {index}: truncated ({len(payload)} of "
                                       f"{length} bytes)")  # fmt: skip
            if masked_crc(payload) != struct.unpack("<I", footer)[0]:
                raise WaymoFormatError(f"{path}: record {index}: data CRC mismatch (corrupt)")
            yield payload
            index += 1


def write_records(path: Path, records: list[bytes]) -> None:
    """A TFRecord file (for tests and fixtures)."""
    with open(path, "wb") as handle:
        for record in records:
            header = struct.pack("<Q", len(record))
            handle.write(header + struct.pack("<I", masked_crc(header)))
            handle.write(record + struct.pack("<I", masked_crc(record)))


def decode_matrix(compressed: bytes, where: str) -> np.ndarray | None:
    """A zlib-compressed MatrixFloat → float32 array of its shape; None when empty."""
    if not compressed:
        return None
    try:
        matrix = message_classes()["MatrixFloat"].FromString(zlib.decompress(compressed))
    except Exception as error:  # zlib.error, protobuf DecodeError
        raise WaymoFormatError(f"{where}: range image cannot be decoded ({error})") from None
    dims = tuple(matrix.shape.dims)
    data = np.asarray(matrix.data, np.float32)
    if not dims or int(np.prod(dims)) != data.size:
        raise WaymoFormatError(f"{where}: range image has {data.size} values for shape {dims}")
    return data.reshape(dims)


def _transform(message, where: str) -> np.ndarray:
    values = np.asarray(message.transform, np.float64)
    if values.size != 16:
        raise WaymoFormatError(f"{where}: transform has {values.size} values, expected 16")
    return values.reshape(4, 4)


def decode_frame(record: bytes, path: Path, index: int) -> WaymoFrame:
    """One Frame record → WaymoFrame (vehicle frame)."""
    try:
        message = message_classes()["Frame"].FromString(record)
    except Exception as error:
        raise WaymoFormatError(f"{path}: record {index} is not a Frame ({error})") from None
    segment = message.context.name or path.stem
    frame = WaymoFrame(segment, int(message.timestamp_micros), None, {}, [])
    if message.HasField("pose"):
        frame.vehicle_pose = _transform(message.pose, frame.where())
    for calibration in message.context.laser_calibrations:
        inclinations = np.asarray(calibration.beam_inclinations, np.float64)
        frame.calibrations[calibration.name] = LaserCalibration(
            calibration.name,
            _transform(calibration.extrinsic, frame.where(calibration.name)),
            inclinations if inclinations.size else None,
            calibration.beam_inclination_min,
            calibration.beam_inclination_max,
        )
    for laser in message.lasers:
        where = frame.where(laser.name)
        returns = [
            decode_matrix(laser.ri_return1.range_image_compressed, f"{where}, return 1"),
            decode_matrix(laser.ri_return2.range_image_compressed, f"{where}, return 2"),
        ]
        pose = decode_matrix(laser.ri_return1.range_image_pose_compressed, f"{where}, pose")
        frame.scans.append(LaserScan(laser.name, returns, pose))
    labels = list(message.laser_labels)
    frame.boxes = np.array(
        [[b.center_x, b.center_y, b.center_z, b.length, b.width, b.height, b.heading]
         for b in (label.box for label in labels)],
        np.float64,
    ).reshape(-1, 7)  # fmt: skip
    frame.types = np.array([label.type for label in labels], np.int64)
    frame.num_points = np.array([label.num_lidar_points_in_box for label in labels], np.int64)
    return frame


def read_segment(path: Path) -> Iterator[WaymoFrame]:
    for index, record in enumerate(read_records(path)):
        yield decode_frame(record, path, index)
