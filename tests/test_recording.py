"""Rerun recordings (`dali view --rerun`, `dali detect --rerun`): read back, the entities and
frames are what was logged; TP / FP / missed colouring; a user's file is never replaced."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from toy_scenes import write_toy_dataset

from dali_cli.cli import main
from dali_cli.reporting.recording import Layer, match_to_truth, read_recording, write_recording
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import BoxTable, FrameSet, read_boxes, write_boxes

pytest.importorskip("rerun", reason="the view extra (make test installs it)")

SCAN = dict(beams=16, points_per_beam=200, azimuth_range_deg=(-60.0, 60.0))


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    directory = tmp_path_factory.mktemp("rec") / "frames"
    write_toy_dataset(directory, get_profile("kitti"), frames=5, seed=2, cars_per_frame=3, **SCAN)
    return directory


def test_match_to_truth_takes_each_label_once():
    truth = np.array([[10, 0, 0, 4, 2, 1.5, 0], [20, 5, 0, 4, 2, 1.5, 0]], float)
    pred = np.array(
        [[10.1, 0, 0, 4, 2, 1.5, 0], [10.2, 0, 0, 4, 2, 1.5, 0], [40, 0, 0, 4, 2, 1.5, 0]]
    )
    tp, found = match_to_truth(pred, truth)
    assert tp.tolist() == [True, False, False] and found.tolist() == [True, False]


def test_view_recording_holds_every_frame_and_layer(frames, tmp_path):
    labels = read_boxes(frames)
    pred = labels.boxes.copy()
    pred[::2, 0] += 30.0  # every other box nowhere near its car: a false positive and a miss
    (tmp_path / "pred").mkdir()
    write_boxes(
        tmp_path / "pred",
        BoxTable.from_arrays(labels.frame_id, pred, score=np.full(len(pred), 0.8)),
    )
    out = tmp_path / "v.rrd"
    result = CliRunner().invoke(
        main, ["view", str(frames), "--boxes", f"pred={tmp_path / 'pred'}", "--rerun", str(out)]
    )
    assert result.exit_code == 0, result.output
    seen = read_recording(out)
    assert set(seen) == {"/world/scan", "/world/labels", "/world/pred", "/world/pred_missed"}
    assert all(frames_logged == [0, 1, 2, 3, 4] for frames_logged in seen.values())


def test_tracks_and_the_ego_path_are_logged(frames, tmp_path):
    ids = list(FrameSet(frames).frame_ids)
    poses = np.tile(np.eye(4), (len(ids), 1, 1))
    poses[:, 0, 3] = np.arange(len(ids)) * 1.5
    labels = read_boxes(frames)
    tracked = labels.with_columns(car=np.arange(len(labels)) % 3, score=np.full(len(labels), 0.9))
    counts = write_recording(tmp_path / "t.rrd", FrameSet(frames).iter_frames(),
                             [Layer("tracks", tracked, "tracks")], poses=dict(zip(ids, poses, strict=True)))  # fmt: skip
    seen = read_recording(tmp_path / "t.rrd")
    assert counts == {"frames": 5, "entities": 3, "boxes": len(labels)}
    assert set(seen) == {"/world/scan", "/world/tracks", "/world/ego"}


def test_a_users_file_is_never_replaced_and_a_failure_leaves_nothing(frames, tmp_path):
    mine = tmp_path / "mine.rrd"
    mine.write_bytes(b"my own notes")
    result = CliRunner().invoke(main, ["view", str(frames), "--rerun", str(mine)])
    assert result.exit_code != 0 and mine.read_bytes() == b"my own notes"

    def broken():
        yield from FrameSet(frames).iter_frames()
        raise RuntimeError("a frame failed")

    with pytest.raises(RuntimeError):
        write_recording(tmp_path / "half.rrd", broken(), [])
    assert not list(tmp_path.glob("*half*"))


def test_view_needs_one_of_out_and_rerun(frames, tmp_path):
    result = CliRunner().invoke(main, ["view", str(frames)])
    assert result.exit_code == 2 and "one of --out" in result.output
