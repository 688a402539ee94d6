"""Scan poses (OXTS -> `dali import kitti-raw --poses` -> sequence.parquet) and the
`dali track-pseudo` stage on a parked car seen from a moving ego."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from fixture_copies import writable_copy
from test_tracks import ego_poses

from dali_cli.cli import main
from dali_cli.geometry import bev_iou, wrap_angle
from dali_cli.importers.kitti_raw import read_tracklets
from dali_cli.labels import tracks
from dali_cli.store.artifacts import BoxTable, FrameSet, read_boxes, write_boxes, write_frameset
from dali_cli.store.sequence import (
    SequenceError,
    read_lidar_poses,
    sequence_table,
    write_sequence,
)

DAY = Path(__file__).resolve().parent / "fixtures" / "kitti_raw" / "2011_09_26"
DRIVE = DAY / "2011_09_26_drive_0001_sync"


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def random_poses(count: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    for i in range(count):
        q = rng.normal(size=4)
        w, x, y, z = q / np.linalg.norm(q)
        poses[i, :3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
        poses[i, :3, 3] = rng.uniform(-500, 500, 3)
    return poses


# ---------------------------------------------------------------------------------------------
# Poses: the sequence table and the OXTS import


def test_poses_round_trip_through_the_sequence_table(tmp_path):
    poses = random_poses(5)
    frame_ids = [f"{i:010d}" for i in (3, 4, 7, 8, 9)]
    write_sequence(tmp_path, frame_ids, poses)
    back = read_lidar_poses(tmp_path, frame_ids[::-1])  # any order, by frame id
    np.testing.assert_array_equal(back, poses[::-1])


def test_a_malformed_sequence_table_names_the_file_and_field(tmp_path):
    poses = random_poses(3)
    frame_ids = ["0000000000", "0000000001", "0000000002"]
    with pytest.raises(SequenceError, match="no sequence table"):
        read_lidar_poses(tmp_path, frame_ids)
    write_sequence(tmp_path, frame_ids[:2], poses[:2])
    with pytest.raises(SequenceError, match=r"sequence.parquet: field 'frame_id'.*0000000002"):
        read_lidar_poses(tmp_path, frame_ids)
    poses[1, 0, 3] = np.nan
    write_sequence(tmp_path, frame_ids, poses)
    with pytest.raises(
        SequenceError, match=r"column 'lidar_pose_03' is NaN/inf for frame '0000000001'"
    ):
        read_lidar_poses(tmp_path, frame_ids)
    poses[1, 0, 3] = 0.0
    poses[2, :3, :3] *= 2.0  # a scaled matrix is no rotation
    write_sequence(tmp_path, frame_ids, poses)
    with pytest.raises(SequenceError, match="frame '0000000002' are not a rotation"):
        read_lidar_poses(tmp_path, frame_ids)
    path = tmp_path / "sequence.parquet"
    good = pq.read_table(path)
    for table, message in (
        (good.drop_columns(["lidar_pose_12"]), r"column 'lidar_pose_12' missing \(the lidar_pose"),
        (
            pa.concat_tables([good, good.slice(0, 1)]),
            r"field 'frame_id': frame '0000000000' appears twice",
        ),
        (good.append_column("time_s", pa.array(["a", "b", "c"])), r"column 'time_s' is string"),
        (good.drop_columns(["index"]), r"column 'index' missing"),
    ):
        pq.write_table(table, path)
        with pytest.raises(SequenceError, match=r"sequence.parquet: " + message) as error:
            read_lidar_poses(tmp_path, frame_ids)
        assert "\n" not in str(error.value)


def test_oxts_poses_put_the_parked_cars_of_two_scans_in_one_place(tmp_path):
    out = tmp_path / "drive"
    result = invoke("import", "kitti-raw", DRIVE, "--poses", "--no-progress", "--out", out)
    assert result.exit_code == 0, result.output
    frame_ids = list(FrameSet(out).frame_ids)
    poses = read_lidar_poses(out, frame_ids)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-9)
    # the ego drove ~1.3 m between the scans (10 Hz, ~13 m/s), forward along its own x
    step = poses[1, :3, 3]
    assert 0.8 < np.linalg.norm(step) < 2.0 and step[0] > 0.9 * np.linalg.norm(step)
    # every tracklet seen in both scans is a parked car: one world position, one heading
    poses_by_frame = {int(f): pose for f, pose in zip(frame_ids, poses, strict=True)}
    tracklets = read_tracklets(DRIVE / "tracklet_labels.xml")
    both = 0
    for track in np.unique(tracklets.track):
        rows = np.flatnonzero(
            (tracklets.track == track) & np.isin(tracklets.frame, list(poses_by_frame))
        )
        if len(rows) < 2 or tracklets.label[rows[0]] != "Car":
            continue
        world = np.concatenate(
            [
                tracks.boxes_to_world(
                    tracklets.boxes()[[row]], poses_by_frame[tracklets.frame[row]]
                )
                for row in rows
            ]
        )
        assert np.linalg.norm(world[1, :2] - world[0, :2]) < 0.3, track
        assert abs(wrap_angle(world[1, 6] - world[0, 6])) < np.radians(2), track
        both += 1
    assert both >= 4


def test_the_import_without_poses_writes_no_sequence_table(tmp_path):
    out = tmp_path / "drive"
    assert invoke("import", "kitti-raw", DRIVE, "--no-progress", "--out", out).exit_code == 0
    assert not (out / "sequence.parquet").exists()
    assert "poses" not in json.loads((out / "manifest.json").read_text())["params"]


@pytest.mark.parametrize(
    "damage, expected",
    [
        (lambda text: text.replace(text.split()[5], "north", 1), r"field 'yaw' is not a number"),
        (lambda text: " ".join(text.split()[:4]), r"field 'pitch' missing"),
        (lambda text: text + "\n" + text, r"one line, the file has 2"),
    ],
)
def test_a_malformed_oxts_record_is_a_one_line_error_naming_file_and_field(
    tmp_path, damage, expected
):
    day = writable_copy(DAY, tmp_path / "2011_09_26")
    record = day / DRIVE.name / "oxts" / "data" / "0000000013.txt"
    record.write_text(damage(record.read_text()))
    result = invoke("import", "kitti-raw", day / DRIVE.name, "--poses", "--out", tmp_path / "o")
    assert result.exit_code == 1
    message = result.output.strip()
    assert "0000000013.txt" in message and len(message.splitlines()) == 1
    assert re.search(expected, message), message
    assert not (tmp_path / "o").exists()


def test_a_missing_oxts_record_names_the_file(tmp_path):
    day = writable_copy(DAY, tmp_path / "2011_09_26")
    (day / DRIVE.name / "oxts" / "data" / "0000000012.txt").unlink()
    result = invoke("import", "kitti-raw", day / DRIVE.name, "--poses", "--out", tmp_path / "o")
    assert result.exit_code == 1
    assert "0000000012.txt: OXTS record not found" in result.output


# ---------------------------------------------------------------------------------------------
# The stage


def car_points(box: np.ndarray, count: int, rng) -> np.ndarray:
    """`(count, 4)` points spread inside `box` `(7,)` (LiDAR frame)."""
    local = rng.uniform(-0.45, 0.45, (count, 3)) * box[3:6]
    c, s = np.cos(box[6]), np.sin(box[6])
    xy = local[:, :2] @ np.array([[c, s], [-s, c]]) + box[:2]
    return np.c_[xy, local[:, 2] + box[2], np.full(count, 0.5)].astype(np.float32)


def sequence_target(tmp_path: Path, frames: int = 12):
    """A target of `frames` scans from a moving ego with a parked car in each (points and
    poses), and pseudo labels: the car found in all scans but 4, 5, 6 and 9, a clutter box
    scored 0.9 in scan 3 only."""
    rng = np.random.default_rng(0)
    poses = ego_poses(frames)
    car = np.array([25.0, 6.0, -0.8, 4.2, 1.8, 1.5, 0.3])
    local = np.concatenate([tracks.boxes_from_world(car[None], pose) for pose in poses])
    frame_ids = [f"{i:010d}" for i in range(frames)]
    target = tmp_path / "target"
    clutter = np.array([15.0, -8.0, -0.8, 3.9, 1.6, 1.5, 1.0])
    write_frameset(
        target,
        (
            (frame_id, np.vstack([car_points(local[i], 60, rng), car_points(clutter, 30, rng)]))
            for i, frame_id in enumerate(frame_ids)
        ),
        "kitti",
    )
    write_sequence(target, frame_ids, poses)
    found = [i for i in range(frames) if i not in (4, 5, 6, 9)]
    boxes = local[found] + np.c_[rng.normal(0, 0.1, (len(found), 2)), np.zeros((len(found), 5))]
    table = BoxTable.from_arrays(
        [frame_ids[i] for i in found] + [frame_ids[3]],
        np.vstack([boxes, clutter]),
        score=np.r_[np.full(len(found), 0.6), 0.9],
        num_points=np.r_[np.full(len(found), 60), 30],
    )
    pseudo = tmp_path / "pseudo"
    pseudo.mkdir()
    write_boxes(pseudo, table)
    (pseudo / "scale.json").write_text(json.dumps({"scale": 1.2}) + "\n")
    return target, pseudo, local, frame_ids


def test_track_pseudo_places_the_parked_car_in_every_scan_and_drops_clutter(tmp_path):
    target, pseudo, truth, frame_ids = sequence_target(tmp_path)
    out = tmp_path / "tracked"
    result = invoke("track-pseudo", "--pseudo", pseudo, "--data", target, "--out", out)
    assert result.exit_code == 0, result.output
    table = read_boxes(out)
    # the car in all 12 scans, the 4 it was missed in included; the clutter box (one scan,
    # scored above the car) nowhere
    assert sorted(table.frame_id) == frame_ids
    for row, frame_id in enumerate(table.frame_id):
        i = frame_ids.index(frame_id)
        assert bev_iou(table.boxes[[row]], truth[[i]])[0, 0] > 0.8
    np.testing.assert_allclose(table["score"], 0.6, rtol=1e-6)
    assert (table["num_points"] >= 60).all()
    assert set(table["track"]) == {0} and table["parked"].all()
    assert (out / "scale.json").read_text() == (pseudo / "scale.json").read_text()
    # a score cut above the car's median score keeps nothing
    again = invoke(
        "track-pseudo", "--pseudo", pseudo, "--data", target, "--track-score-min", "0.7",
        "--out", tmp_path / "strict",
    )  # fmt: skip
    assert again.exit_code == 0, again.output
    assert len(read_boxes(tmp_path / "strict")) == 0


def test_track_pseudo_without_poses_says_how_to_get_them(tmp_path):
    target, pseudo, _, _ = sequence_target(tmp_path, frames=4)
    (target / "sequence.parquet").unlink()
    result = invoke("track-pseudo", "--pseudo", pseudo, "--data", target, "--out", tmp_path / "o")
    assert result.exit_code == 1
    assert "sequence.parquet: no sequence table" in result.output
    assert "dali import kitti-raw --poses" in result.output


def test_track_pseudo_without_lidar_poses_names_the_missing_column(tmp_path):
    target, pseudo, _, frame_ids = sequence_target(tmp_path, frames=4)
    table = sequence_table(frame_ids, camera_poses=ego_poses(4))  # odometry without calib.txt
    pq.write_table(table, target / "sequence.parquet")
    result = invoke("track-pseudo", "--pseudo", pseudo, "--data", target, "--out", tmp_path / "o")
    assert result.exit_code == 1
    assert "sequence.parquet: column 'lidar_pose_00' missing" in result.output
    assert len(result.output.strip().splitlines()) == 1


def merged_drives(tmp_path: Path):
    """Two drives `a`, `b` of the same scans (sequence_target: the same poses, the car at the
    same world place), merged, and their pseudo labels under the merged frame ids."""
    drives = {name: sequence_target(tmp_path / name) for name in ("a", "b")}
    merged = tmp_path / "merged"
    args = [f"--in={name}={drive[0]}" for name, drive in drives.items()]
    result = invoke("merge", *args, "--out", merged, "--no-progress")
    assert result.exit_code == 0, result.output
    tables = []
    for name, (_, pseudo, _, _) in drives.items():
        table = read_boxes(pseudo)
        tables.append(
            table.with_columns(
                frame_id=np.array([f"{name}-{f}" for f in table.frame_id], dtype=object)
            )
        )
    pseudo = tmp_path / "merged-pseudo"
    pseudo.mkdir()
    write_boxes(pseudo, BoxTable.concat(tables))
    return drives, merged, pseudo


def test_merge_keeps_each_drives_poses_and_track_pseudo_never_links_across_drives(tmp_path):
    drives, merged, pseudo = merged_drives(tmp_path)
    frame_ids = FrameSet(merged).frame_ids
    table = pq.read_table(merged / "sequence.parquet").to_pydict()
    assert table["recording"] == ["a"] * 12 + ["b"] * 12
    np.testing.assert_allclose(
        read_lidar_poses(merged, frame_ids), np.r_[ego_poses(12), ego_poses(12)]
    )
    out = tmp_path / "tracked"
    result = invoke("track-pseudo", "--pseudo", pseudo, "--data", merged, "--out", out)
    assert result.exit_code == 0, result.output
    boxes = read_boxes(out)
    # one car per drive (tracked as one over the 24 scans they would be one car, its parked
    # box placed in both drives' scans): each placed in its own drive's 12 scans only
    assert set(boxes["track"]) == {0, 1}
    for track, name in ((0, "a"), (1, "b")):
        ids = sorted(boxes.frame_id[boxes["track"] == track])
        assert ids == [f"{name}-{f:010d}" for f in range(12)]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["recordings"] == 2 and summary["parked_cars"] == 2
    # a merged set whose table has no recording column (an older merge): the frame ids' set
    # names group the scans
    pq.write_table(
        pq.read_table(merged / "sequence.parquet").drop_columns(["recording"]),
        merged / "sequence.parquet",
    )
    again = invoke("track-pseudo", "--pseudo", pseudo, "--data", merged, "--out", tmp_path / "t2")
    assert again.exit_code == 0, again.output
    assert set(read_boxes(tmp_path / "t2")["track"]) == {0, 1}


def test_ppcg_reads_the_tracked_labels_as_it_reads_pseudo_labels(tmp_path):
    target, pseudo, _, frame_ids = sequence_target(tmp_path, frames=6)
    tracked, library = tmp_path / "tracked", tmp_path / "library"
    assert (
        invoke("track-pseudo", "--pseudo", pseudo, "--data", target, "--out", tracked).exit_code
        == 0
    )
    built = invoke("library", "build", "--procedural", 1, "--seed", 1, "--out", library)
    assert built.exit_code == 0, built.output
    for stage in ("ppcg-rc", "ppcg-cf"):
        result = invoke(
            stage, "--data", target, "--boxes", tracked, "--library", library,
            "--no-progress", "--out", tmp_path / stage,
        )  # fmt: skip
        assert result.exit_code == 0, result.output
        assert sorted(FrameSet(tmp_path / stage).frame_ids) == frame_ids
