"""`dali register` (stages.register): a target's scans registered into a sequence table,
recording by recording in index order, its errors, and `dali track-pseudo --poses`."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from click.testing import CliRunner
from street_scans import scan, trajectory
from test_track_pseudo import sequence_target

from dali_cli.cli import main
from dali_cli.store.artifacts import FrameSet, read_boxes, write_frameset
from dali_cli.store.sequence import read_lidar_poses, read_sequence, write_sequence


def invoke(*args):
    """The CLI; `dali register` without its progress bar, so the output is its messages."""
    words = [str(a) for a in args]
    if words[0] == "register":
        words.append("--no-progress")
    return CliRunner().invoke(main, words)


def street_target(directory: Path, truth: np.ndarray, order=None, table: bool = False) -> list:
    """A frame set of the street scanned from `truth` `(n, 4, 4)`, frames written in `order`
    (positions; default in order), with a sequence table (index, time_s; no poses) when
    `table`. Returns the frame ids by index."""
    frame_ids = [f"{i:010d}" for i in range(len(truth))]
    order = range(len(truth)) if order is None else order
    write_frameset(directory, ((frame_ids[i], scan(truth[i], seed=i)) for i in order), "kitti")
    if table:
        ids = [frame_ids[i] for i in order]
        write_sequence(directory, ids, index=np.array(order), time_s=0.1 * np.array(order))
    return frame_ids


def relative(poses: np.ndarray) -> np.ndarray:
    return np.linalg.inv(poses[0]) @ poses


def test_register_writes_the_scans_poses_and_skips_when_up_to_date(tmp_path):
    truth = trajectory(np.full(5, 1.2))
    # written backwards: the table's index, not the frame set's order, orders the scans
    frame_ids = street_target(tmp_path / "target", truth, order=[5, 4, 3, 2, 1, 0], table=True)
    out = tmp_path / "poses"
    result = invoke("register", "--data", tmp_path / "target", "--out", out)
    assert result.exit_code == 0, result.output
    assert "register: 6 scans in 1 recording(s), 6.0 m, 0 not converged" in result.output
    poses = read_lidar_poses(out, frame_ids)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(poses[:, :3, 3], truth[:, :3, 3], atol=0.05)
    table = read_sequence(out).to_pydict()
    assert table["frame_id"] == frame_ids[::-1] and table["index"] == [5, 4, 3, 2, 1, 0]
    np.testing.assert_allclose(table["time_s"], [0.5, 0.4, 0.3, 0.2, 0.1, 0.0])
    assert "recording" not in table
    summary = json.loads((out / "summary.json").read_text())["recordings"][""]
    assert summary["scans"] == 6 and abs(summary["path_length_m"] - 6.0) < 0.1
    assert abs(summary["median_step_m"] - 1.2) < 0.05 and summary["not_converged"] == []
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stage"] == "register" and set(manifest["inputs"]) == {"target"}
    assert manifest["params"]["voxel_m"] == 1.0
    assert not (tmp_path / "target" / "summary.json").exists()
    again = invoke("register", "--data", tmp_path / "target", "--out", out)
    assert again.exit_code == 0 and "up to date" in again.output


def test_a_merged_target_is_registered_recording_by_recording(tmp_path):
    truths = {"a": trajectory(np.full(3, 1.2)), "b": trajectory(np.full(3, 1.0), -0.01)[::-1]}
    for name, truth in truths.items():
        street_target(tmp_path / name, truth)  # no sequence table: frame ids' order
    merged = tmp_path / "merged"
    done = invoke("merge", "--in", f"a={tmp_path / 'a'}", "--in", f"b={tmp_path / 'b'}",
                  "--out", merged, "--no-progress")  # fmt: skip
    assert done.exit_code == 0, done.output
    assert not (merged / "sequence.parquet").exists()
    out = tmp_path / "poses"
    result = invoke("register", "--data", merged, "--out", out)
    assert result.exit_code == 0, result.output
    frame_ids = FrameSet(merged).frame_ids
    table = pq.read_table(out / "sequence.parquet").to_pydict()
    assert table["recording"] == ["a"] * 4 + ["b"] * 4
    poses = read_lidar_poses(out, frame_ids)
    for k, truth in enumerate(truths.values()):  # each from its own first scan
        np.testing.assert_allclose(poses[4 * k : 4 * k + 4, :3, 3], relative(truth)[:, :3, 3],
                                   atol=0.05)  # fmt: skip
    summary = json.loads((out / "summary.json").read_text())["recordings"]
    assert sorted(summary) == ["a", "b"] and summary["b"]["scans"] == 4


def test_a_recording_of_one_scan_is_an_error_and_nothing_is_written(tmp_path):
    street_target(tmp_path / "a", trajectory(np.full(2, 1.2)))
    street_target(tmp_path / "b", trajectory(np.zeros(0)))
    merged = tmp_path / "merged"
    done = invoke("merge", "--in", f"a={tmp_path / 'a'}", "--in", f"b={tmp_path / 'b'}",
                  "--out", merged, "--no-progress")  # fmt: skip
    assert done.exit_code == 0, done.output
    result = invoke("register", "--data", merged, "--out", tmp_path / "poses")
    assert result.exit_code == 1
    assert result.output.strip().splitlines() == [
        f"Error: {merged / 'frames.zarr'}: recording 'b' has 1 scan ('b-0000000000'): "
        "registration needs at least 2"
    ]
    assert not (tmp_path / "poses").exists()


def test_a_scan_too_empty_to_register_is_named(tmp_path):
    truth = trajectory(np.full(2, 1.2))
    ids = [f"{i:010d}" for i in range(3)]
    near = scan(truth[2])[:50]
    frames = [(ids[0], scan(truth[0])), (ids[1], scan(truth[1])), (ids[2], near)]
    write_frameset(tmp_path / "target", frames, "kitti")
    result = invoke("register", "--data", tmp_path / "target", "--out", tmp_path / "poses")
    assert result.exit_code == 1
    message = result.output.strip()
    assert len(message.splitlines()) == 1 and "frames.zarr, frame '0000000002': " in message
    assert "fewer than the 100 registration needs" in message
    assert not (tmp_path / "poses").exists()
    empty_range = invoke("register", "--data", tmp_path / "target", "--min-range-m", "90",
                         "--out", tmp_path / "poses")  # fmt: skip
    assert empty_range.exit_code == 2 and "--min-range-m / --max-range-m" in empty_range.output


def test_track_pseudo_reads_poses_from_another_directory(tmp_path):
    target, pseudo, _, frame_ids = sequence_target(tmp_path)
    own = tmp_path / "own"
    assert invoke("track-pseudo", "--pseudo", pseudo, "--data", target, "--out", own).exit_code == 0
    poses = tmp_path / "registered"
    poses.mkdir()
    shutil.move(target / "sequence.parquet", poses / "sequence.parquet")
    result = invoke("track-pseudo", "--pseudo", pseudo, "--data", target, "--poses", poses,
                    "--out", tmp_path / "other")  # fmt: skip
    assert result.exit_code == 0, result.output
    boxes = pq.read_table(own / "boxes.parquet")
    assert len(read_boxes(own)) == 12 and pq.read_table(tmp_path / "other/boxes.parquet").equals(
        boxes
    )
    first, second = (
        json.loads((d / "manifest.json").read_text()) for d in (own, tmp_path / "other")
    )
    assert first["params"] == second["params"]  # --poses is an input, not a parameter
    assert "poses" not in first["inputs"] and second["inputs"]["poses"][0]["path"] == str(poses)
    # poses that lack a scan of the target
    write_sequence(poses, frame_ids[:-1], read_lidar_poses(poses, frame_ids[:-1]))
    short = invoke("track-pseudo", "--pseudo", pseudo, "--data", target, "--poses", poses,
                   "--out", tmp_path / "short")  # fmt: skip
    assert short.exit_code == 1 and not (tmp_path / "short").exists()
    assert f"no pose for frame '{frame_ids[-1]}' (--poses must cover the scans of" in short.output
