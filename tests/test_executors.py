"""The per-frame stages on the executors: a local Ray instance (started once for this
module) and the local process pool give the serial run's artifact byte for byte; workers load
their models once; shards are written by the workers into the artifact's temporary directory and
merged one by one; a failing frame leaves no artifact and the error names it."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from toy_scenes import SMALL_NET

from dali_cli.cli import main
from dali_cli.detector.config import DetectorConfig
from dali_cli.detector.infer import save_checkpoint
from dali_cli.detector.model import PillarCenterNet
from dali_cli.executors import Shard, ShardsFailed, plan_shards
from dali_cli.executors.local import LocalExecutor
from dali_cli.store.artifacts import FrameSet, read_boxes
from dali_cli.store.manifest import read_manifest

FRAMES = 6


@pytest.fixture(scope="module")
def ray_session():
    """One local Ray instance for the module: 2 CPUs, no dashboard, a small object store."""
    import ray

    ray.init(
        address="local",  # our own, even if another Ray runs on this machine
        num_cpus=2,
        include_dashboard=False,
        object_store_memory=80 * 2**20,
        log_to_driver=False,
        logging_level="WARNING",
    )
    yield ray
    ray.shutdown()


def dali(*args: str) -> str:
    result = CliRunner().invoke(main, [str(a) for a in args])
    assert result.exit_code == 0, result.output + repr(result.exception)
    return result.output


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A 6-frame synthetic KITTI target (serial synth), a 2-mesh library and a small random
    detector (its boxes are arbitrary, but many, and deterministic)."""
    root = tmp_path_factory.mktemp("executors")
    dali("synth", "--sensor", "kitti", "--frames", FRAMES, "--seed", 5, "--workers", 1,
         "--out", root / "target")  # fmt: skip
    dali("library", "build", "--procedural", 2, "--seed", 1, "--out", root / "library")
    torch.manual_seed(0)
    (root / "model").mkdir()
    save_checkpoint(
        root / "model", PillarCenterNet(DetectorConfig(**SMALL_NET)), {"provenance": {}}
    )
    return root


def same_artifact(a: Path, b: Path) -> dict:
    """Assert two stage outputs hold the same bytes (the manifest's content hash covers every
    file but the manifest) and the same counts; returns b's manifest."""
    first, second = read_manifest(a), read_manifest(b)
    assert first["content_hash"] == second["content_hash"]
    assert first["outputs"]["counts"] == second["outputs"]["counts"]
    return second


def check_workers(manifest: dict, engine: str, workers: int, load: str | None) -> None:
    """The run's executor record: the engine, `workers` worker processes other than this one,
    more shards than workers (so workers were reused), `load` loaded once by each."""
    report = manifest["executor"]
    assert report["engine"] == engine and report["workers"] == workers
    per_worker = report["per_worker"]
    assert 1 <= len(per_worker) <= workers
    assert all(int(name.rpartition(":")[2]) != os.getpid() for name in per_worker)
    assert sum(w["shards"] for w in per_worker.values()) > len(per_worker)
    assert sum(w["frames"] for w in per_worker.values()) == FRAMES
    for record in per_worker.values():
        assert record["loads"] == ({load: 1} if load else {})


def test_plan_shards_cover_every_frame_once_in_batch_multiples():
    ids = [f"{i:06d}" for i in range(103)]
    for workers, multiple in ((1, 1), (2, 8), (64, 4), (3, 1)):
        shards = plan_shards(ids, workers, multiple=multiple, max_frames=32)
        assert [s.index for s in shards] == list(range(len(shards)))
        assert shards[0].start == 0 and shards[-1].stop == len(ids)
        assert all(a.stop == b.start for a, b in zip(shards, shards[1:], strict=False))
        assert all((s.stop - s.start) % multiple == 0 for s in shards[:-1])
        assert all(s.stop - s.start <= 32 for s in shards)
        assert sum(len(s.frame_ids) for s in shards) == len(ids)
    assert len(plan_shards(ids, 2, max_frames=64)) >= 8  # about 4 per worker: load balance


@pytest.mark.slow  # a local Ray cluster, end to end
def test_synth_on_ray_and_local_pool_equals_serial(data, ray_session, tmp_path):
    args = ["synth", "--sensor", "kitti", "--frames", FRAMES, "--seed", 5]
    dali(*args, "--executor", "ray", "--workers", 2, "--out", tmp_path / "ray")
    same_artifact(data / "target", tmp_path / "ray")
    check_workers(read_manifest(tmp_path / "ray"), "ray", 2, None)
    dali(*args, "--executor", "local", "--workers", 2, "--out", tmp_path / "pool")
    same_artifact(data / "target", tmp_path / "pool")
    # and the frames themselves, bit for bit (not only the hash the manifest records)
    serial, ray_frames = FrameSet(data / "target"), FrameSet(tmp_path / "ray")
    assert serial.frame_ids == ray_frames.frame_ids
    for index in range(FRAMES):
        assert np.array_equal(serial.frame(index), ray_frames.frame(index))


@pytest.mark.parametrize("stage", ["ppcg-rc", "ppcg-cf"])
@pytest.mark.slow  # a local Ray cluster, end to end
def test_ppcg_on_ray_equals_serial_and_loads_the_library_once_per_actor(
    data, ray_session, tmp_path, stage
):
    args = [stage, "--data", data / "target", "--boxes", data / "target",
            "--library", data / "library", "--no-progress"]  # fmt: skip
    dali(*args, "--out", tmp_path / "serial")
    dali(*args, "--executor", "ray", "--workers", 2, "--out", tmp_path / "ray")
    manifest = same_artifact(tmp_path / "serial", tmp_path / "ray")
    mode = stage.split("-")[1]
    assert manifest["outputs"]["counts"][f"boxes_{mode}"] > 0  # boxes were really re-cast
    check_workers(manifest, "ray", 2, "model library")
    serial, ray_boxes = read_boxes(tmp_path / "serial"), read_boxes(tmp_path / "ray")
    for name in serial.columns:
        assert np.array_equal(serial[name], ray_boxes[name]), name


@pytest.mark.slow  # a local Ray cluster, end to end
def test_pseudo_label_on_ray_equals_serial_at_the_same_torch_threads(data, ray_session, tmp_path):
    """Each worker runs torch on one thread; the serial reference does too (`--threads 1`:
    torch's results differ in the last bits between thread counts, whatever the engine)."""
    args = ["pseudo-label", "--model", data / "model", "--data", data / "target",
            "--scale", "1.05", "--score-min", "0.05", "--batch-size", 2, "--no-progress"]  # fmt: skip
    dali(*args, "--threads", 1, "--out", tmp_path / "serial")
    dali(*args, "--executor", "ray", "--workers", 2, "--out", tmp_path / "ray")
    manifest = same_artifact(tmp_path / "serial", tmp_path / "ray")
    assert manifest["outputs"]["counts"]["boxes"] > 0
    check_workers(manifest, "ray", 2, "detector")
    dali(*args, "--executor", "local", "--workers", 2, "--out", tmp_path / "pool")
    check_workers(same_artifact(tmp_path / "serial", tmp_path / "pool"), "local", 2, "detector")


@pytest.mark.slow  # a local Ray cluster, end to end
def test_eval_on_ray_equals_serial(data, ray_session, tmp_path, monkeypatch):
    import dali_cli.runtime.machine as runtime

    monkeypatch.setattr(runtime, "available_cores", lambda: 1)  # the workers' one torch thread
    args = ["eval", "--model", data / "model", "--data", data / "target", "--scale", "1.0"]
    dali(*args, "--out", tmp_path / "serial" / "metrics.json")
    output = dali(*args, "--executor", "ray", "--workers", 2,
                  "--out", tmp_path / "ray" / "metrics.json")  # fmt: skip
    assert "eval: ran on ray with 2 worker(s)" in output
    for name in ("metrics.json", "predictions.parquet"):
        assert (tmp_path / "serial" / name).read_bytes() == (tmp_path / "ray" / name).read_bytes()
    predictions = read_boxes(tmp_path / "ray" / "predictions.parquet")
    assert len(predictions) > 0
    assert sorted(p.name for p in (tmp_path / "ray").iterdir()) == [
        "metrics.json",
        "predictions.parquet",
    ]  # the shard folder is gone


def damaged_copy(target: Path, where: Path, frame: int) -> Path:
    """A copy of the frame set whose frame `frame` has a NaN coordinate."""
    import zarr

    shutil.copytree(target, where)
    frames = FrameSet(where)
    points = zarr.open_group(str(frames.path), mode="r+")["points"]
    points[int(frames.offsets[frame]), 0] = np.nan
    return where


@pytest.mark.slow  # a local Ray cluster, end to end
def test_a_failing_frame_on_ray_leaves_no_artifact_and_is_named(data, ray_session, tmp_path):
    target = damaged_copy(data / "target", tmp_path / "target", frame=4)
    out = tmp_path / "rc"
    result = CliRunner().invoke(
        main,
        ["ppcg-rc", "--data", str(target), "--boxes", str(target),
         "--library", str(data / "library"), "--no-progress", "--executor", "ray",
         "--workers", "2", "--out", str(out)],
    )  # fmt: skip
    assert result.exit_code != 0
    assert "frame '000004'" in result.output and "NaN" in result.output
    assert "000003" not in result.output  # only the failing frame is named
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["target"]  # no temporary leftovers


@pytest.mark.slow  # a local Ray cluster, end to end
def test_shards_are_written_by_workers_into_the_temporary_directory_and_merged_one_by_one(
    data, ray_session, tmp_path, monkeypatch
):
    """While the driver merges shard k, shard k's files are in <out>.tmp-<pid>/shards, written by
    another process, the shards merged before are gone, and <out> does not exist yet."""
    import dali_cli.executors as executors

    original = executors.shard_results
    seen = []

    def watching(executor, factory, shards, directory):
        for shard, shard_dir, summary in original(executor, factory, shards, directory):
            root = shard_dir.parent
            assert root == Path(directory) / "shards"
            assert Path(directory).name.startswith(f"rc.tmp-{os.getpid()}-")
            assert not (tmp_path / "rc").exists()
            assert (shard_dir / "points.npy").is_file()
            assert sorted(p.name for p in root.iterdir())[0] == shard_dir.name
            assert int(summary["worker"].rpartition(":")[2]) != os.getpid()
            seen.append(shard.index)
            yield shard, shard_dir, summary

    monkeypatch.setattr(executors, "shard_results", watching)
    dali("ppcg-rc", "--data", data / "target", "--boxes", data / "target", "--library",
         data / "library", "--no-progress", "--executor", "ray", "--workers", 2,
         "--out", tmp_path / "rc")  # fmt: skip
    assert seen == list(range(len(seen))) and len(seen) > 2
    assert not (tmp_path / "rc" / "shards").exists()
    assert FrameSet(tmp_path / "rc").frame_ids == FrameSet(data / "target").frame_ids


class _FailsOnFrame:
    """A worker factory whose worker fails on one frame (the local engine runs it in-process or
    in spawned processes, which import this test module by name)."""

    def __init__(self, bad: str):
        self.bad = bad

    def __call__(self):
        return self

    def run(self, shard: Shard, directory: Path) -> dict:
        from dali_cli.executors import naming_frames

        for frame_id in shard.frame_ids:
            with naming_frames(frame_id):
                if frame_id == self.bad:
                    raise ValueError("injected")
        (directory / "done").write_text(json.dumps(shard.frame_ids))
        return {}


def test_local_executor_stops_at_a_failing_frame_and_names_it(tmp_path):
    ids = [f"{i:06d}" for i in range(10)]
    shards = plan_shards(ids, 1, max_frames=3)
    with LocalExecutor(1) as executor:
        merged = []
        with pytest.raises(ShardsFailed) as caught:
            for shard, _ in executor.map_shards(_FailsOnFrame("000004"), shards, tmp_path):
                merged.append(shard.index)
    assert "frame '000004': ValueError: injected" in str(caught.value.message)
    assert merged == [0]  # shard 1 holds frame 4: nothing after it is handed to the merge


@pytest.mark.slow  # a local Ray cluster, end to end
def test_lost_ray_workers_are_restarted_and_their_shards_retried(
    data, ray_session, tmp_path, monkeypatch
):
    """Both actors are killed while shards are queued and running: Ray restarts them (each
    loads the library again, once) and reruns their shards; the artifact is still the serial
    one."""
    from dali_cli.executors.ray import RayExecutor

    original = RayExecutor._completions
    killed = []

    def killing(executor, factory, shards, directory):
        # at the first completion, not at the first merge in shard order (that can come after
        # every shard is done): with 2 actors and 6 one-frame shards, 4 are still queued
        for shard, result in original(executor, factory, shards, directory):
            if not killed:
                for actor in executor._actors:
                    ray_session.kill(actor, no_restart=False)
                killed.append(shard.index)
            yield shard, result

    monkeypatch.setattr(RayExecutor, "_completions", killing)
    args = ["ppcg-cf", "--data", data / "target", "--boxes", data / "target",
            "--library", data / "library", "--no-progress"]  # fmt: skip
    dali(*args, "--out", tmp_path / "serial")
    dali(*args, "--executor", "ray", "--workers", 2, "--out", tmp_path / "ray")
    manifest = same_artifact(tmp_path / "serial", tmp_path / "ray")
    per_worker = manifest["executor"]["per_worker"]
    assert killed and len(per_worker) >= 3  # the restarted actors are new processes
    assert all(record["loads"] == {"model library": 1} for record in per_worker.values())
