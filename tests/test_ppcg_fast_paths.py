"""PPCG's fast paths give the same bits as the reference paths they replace.

- raw chunk I/O (dali_cli.store.raw_chunks) writes the very files Zarr writes and reads the same points
- CF's ray generation (window.windows_directions) equals window_rays box by box
- cf.median equals np.median
"""

from __future__ import annotations

import numpy as np
import pytest

from dali_cli.ppcg.cf import median
from dali_cli.ppcg.window import AngularWindows, box_windows, window_rays, windows_directions
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import FrameSet, FrameSetWriter


def _frames(rng, count=7):
    sizes = rng.integers(0, 40, count)
    sizes[2] = 0  # an empty frame
    return [(f"f{i}", rng.normal(0, 30, (n, 4)).astype(np.float32)) for i, n in enumerate(sizes)]


def _zarr_reference(directory, frames, chunk_points):
    """The same frames written through Zarr itself with the layout FrameSetWriter asks for."""
    import zarr
    from zarr.codecs import Crc32cCodec

    group = zarr.open_group(str(directory / "frames.zarr"), mode="w", zarr_format=3)
    array = group.create_array(
        "points",
        shape=(0, 4),
        chunks=(chunk_points, 4),
        dtype="float32",
        config={"write_empty_chunks": True},
        compressors=(Crc32cCodec(),),
    )
    data = np.concatenate([p for _, p in frames])
    array.resize((len(data), 4))
    array[:] = data
    return data


@pytest.mark.parametrize("chunk_points", [8, 13, 1000])
def test_raw_writer_writes_the_files_zarr_writes(tmp_path, chunk_points):
    frames = _frames(np.random.default_rng(chunk_points))
    with FrameSetWriter(tmp_path / "fast", "kitti", chunk_points=chunk_points, compress=False) as w:
        for frame_id, points in frames:
            w.append(frame_id, points)
    data = _zarr_reference(tmp_path / "zarr", frames, chunk_points)
    fast = tmp_path / "fast" / "frames.zarr" / "points"
    reference = tmp_path / "zarr" / "frames.zarr" / "points"
    names = sorted(p.relative_to(reference) for p in reference.rglob("*") if p.is_file())
    assert names == sorted(p.relative_to(fast) for p in fast.rglob("*") if p.is_file())
    assert len(names) == 1 + -(-len(data) // chunk_points)  # zarr.json and every chunk
    for name in names:
        assert (fast / name).read_bytes() == (reference / name).read_bytes(), name
    # and the direct reader returns what Zarr's own reader returns, frame by frame
    frameset = FrameSet(tmp_path / "fast")
    assert frameset._raw
    np.testing.assert_array_equal(frameset.load_all()[0], np.asarray(frameset._points[:]))
    for (frame_id, points), (read_id, read) in zip(frames, frameset.iter_frames(), strict=True):
        assert read_id == frame_id
        np.testing.assert_array_equal(read, points)
    for index in (0, 3, len(frames) - 1):
        np.testing.assert_array_equal(frameset.frame(index), frames[index][1])


def test_compressed_frame_sets_keep_zarrs_reader(tmp_path):
    frames = _frames(np.random.default_rng(0))
    with FrameSetWriter(tmp_path, "kitti", chunk_points=16) as writer:
        for frame_id, points in frames:
            writer.append(frame_id, points)
    frameset = FrameSet(tmp_path)
    assert not frameset._raw
    for (_, points), (_, read) in zip(frames, frameset.iter_frames(), strict=True):
        np.testing.assert_array_equal(read, points)


def _random_windows(rng, count):
    """Boxes all around the sensor, near (one contains the sensor) and up to 150 m away."""
    angle = rng.uniform(-np.pi, np.pi, count)
    distance = rng.uniform(3.0, 150.0, count)
    distance[0] = 0.5  # the sensor inside the box: the full window
    boxes = np.column_stack(
        [
            distance * np.cos(angle),
            distance * np.sin(angle),
            rng.uniform(-2.0, 0.5, count),
            rng.uniform(3.0, 6.0, count),
            rng.uniform(1.5, 2.2, count),
            rng.uniform(1.3, 2.0, count),
            rng.uniform(-np.pi, np.pi, count),
        ]
    )
    boxes[0, 2] = 0.0  # ... and spans the sensor's height: every ray
    boxes[1, :2] = (-20.0, 1e-3)  # straddles the +-pi azimuth seam
    return box_windows(boxes)


@pytest.mark.parametrize("sensor", ["kitti", "nuscenes", "waymo", "waymo_top"])
def test_windows_directions_equal_window_rays_box_by_box(sensor):
    profile = get_profile(sensor)
    windows = _random_windows(np.random.default_rng(4), 40)
    directions, bounds = windows_directions(profile, windows)
    assert bounds[0] == 0 and bounds[-1] == len(directions)
    for i in range(len(windows)):
        expected = window_rays(
            profile,
            windows.azimuth_lo[i],
            windows.azimuth_hi[i],
            windows.elevation_lo[i],
            windows.elevation_hi[i],
        ).directions
        assert np.array_equal(directions[bounds[i] : bounds[i + 1]], expected), i
    assert bounds[1] == profile.points_per_beam * len(profile.elevations_rad())  # full window


def test_windows_directions_of_no_window():
    empty = np.zeros(0)
    directions, bounds = windows_directions(
        get_profile("kitti"), AngularWindows(empty, empty, empty, empty, empty.astype(bool))
    )
    assert directions.shape == (0, 3) and list(bounds) == [0]


def test_median_has_np_medians_bits():
    rng = np.random.default_rng(1)
    for size in [*range(1, 30), 101, 1000]:
        for values in (
            rng.uniform(0, 1, size).astype(np.float32),
            rng.integers(0, 4, size).astype(np.float32),  # ties
            rng.normal(0, 1e30, size).astype(np.float32),  # a sum that overflows float32
        ):
            expected = np.median(values)
            got = median(values)
            assert got.dtype == expected.dtype
            assert np.array_equal(got, expected, equal_nan=True), (size, values)
