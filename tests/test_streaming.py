"""Streaming training data: frames read from frames.zarr when a sample needs them equal the
frames held in memory (clipping, SN and PTSN scaling, pooling), the on-disk gt-sampling database
equals the in-memory one and is reused, the training loader's batches do not depend on its
number of worker processes, and training on streamed frames gives the weights of training on
frames in memory."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from test_retrain import SMALL, TOY
from toy_scenes import write_toy_dataset

from dali_cli.detector import Augmentation, DetectorConfig, PillarCenterNet, TrainSettings, train
from dali_cli.detector.augment import ObjectDatabase
from dali_cli.detector.data import (
    FramePoints,
    chain_points,
    detection_region,
    load_labeled,
    scale_about_ground,
    size_normalize,
)
from dali_cli.detector.gt_database import cache_root, cached_database
from dali_cli.detector.loader import StepBatches, TrainingSamples, training_loader
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import ChunkCache, FrameSet, write_frameset
from dali_cli.store.atomic_dir import mark_leftover


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    directory = tmp_path_factory.mktemp("stream") / "toy"
    write_toy_dataset(directory, get_profile("kitti"), seed=5, **{**TOY, "frames": 5})
    return directory


@pytest.fixture(scope="module")
def config():
    return DetectorConfig.from_dict(SMALL)


def same_arrays(a: list, b: list) -> bool:
    return len(a) == len(b) and all(
        x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y)
        for x, y in zip(a, b, strict=True)
    )


def test_frame_reads_through_a_bounded_chunk_cache_match_direct_reads(tmp_path):
    rng = np.random.default_rng(0)
    frames = [(f"f{i}", rng.normal(size=(int(n), 4)).astype(np.float32)) for i, n in
              enumerate(rng.integers(0, 900, size=12))]  # fmt: skip
    write_frameset(tmp_path / "set", frames, "kitti", chunk_points=500)  # frames span chunks
    frameset, cache = FrameSet(tmp_path / "set"), ChunkCache(2)
    for index in rng.permutation(12).tolist() + [3, 3, 11]:
        assert np.array_equal(frameset.frame(index, cache), frames[index][1])
    assert len(cache._chunks) <= 2  # bounded


def test_streamed_points_equal_points_in_memory(toy, config):
    memory = load_labeled(toy, config)
    streamed = load_labeled(toy, config, stream=True)
    assert isinstance(streamed.points, FramePoints) and isinstance(memory.points, list)
    assert same_arrays(memory.boxes, streamed.boxes)
    assert same_arrays(memory.points, [streamed.points[i] for i in (0, 1, 2, 3, 4)])
    assert same_arrays(memory.points, list(streamed.points))  # block-wise iteration
    delta = np.array([0.3, -0.1, 0.2])
    for change in (lambda d: size_normalize(d, delta), lambda d: scale_about_ground(d, 0.9)):
        a, b = change(memory), change(streamed)
        assert same_arrays(a.boxes, b.boxes)
        assert same_arrays(a.points, [b.points[i] for i in range(len(b))])
    both = pickle.loads(pickle.dumps(size_normalize(streamed, delta).points))  # a worker's copy
    assert same_arrays(size_normalize(memory, delta).points, list(both))
    pooled = chain_points([streamed.points, memory.points])
    assert same_arrays(memory.points + memory.points, [pooled[i] for i in range(10)])


def test_cached_database_equals_the_in_memory_one_and_is_reused(toy, config, tmp_path):
    region = detection_region(config)
    memory = load_labeled(toy, config)
    streamed = size_normalize(load_labeled(toy, config, stream=True), np.array([0.2, 0.1, 0.0]))
    expected = ObjectDatabase.build(
        size_normalize(memory, np.array([0.2, 0.1, 0.0])).points, streamed.boxes, region=region
    )
    database = cached_database(streamed, region=region, root=tmp_path)
    assert len(expected) > 0 and isinstance(database.points, np.memmap)
    assert np.array_equal(database.boxes, expected.boxes)
    assert np.array_equal(database.offsets, expected.offsets)
    assert np.array_equal(np.asarray(database.points), expected.points)
    assert database.region == expected.region
    abandoned = tmp_path / "gt_database" / "0123.tmp-999999999"  # a writer that died
    abandoned.mkdir()
    mark_leftover(abandoned, abandoned.with_name("0123"), "tmp")
    users = tmp_path / "gt_database" / "mine.tmp-999999998"  # the same name pattern, not dali's
    users.mkdir()
    other_root = cached_database(streamed, region=region, root=tmp_path)
    assert other_root.directory == database.directory and not abandoned.exists()
    assert users.is_dir(), "a directory dali did not mark must never be removed"
    users.rmdir()
    entries = list((tmp_path / "gt_database").iterdir())
    assert len(entries) == 1 and not list(tmp_path.glob("gt_database/*.tmp-*"))
    stamp = (entries[0] / "points.f32").stat().st_mtime_ns
    again = cached_database(streamed, region=region, root=tmp_path)
    assert again.directory == database.directory
    assert (entries[0] / "points.f32").stat().st_mtime_ns == stamp  # reused, not rebuilt
    copy = pickle.loads(pickle.dumps(database))  # a worker maps the file, no copy travels
    assert isinstance(copy.points, np.memmap) and np.array_equal(copy.boxes, database.boxes)
    other = cached_database(load_labeled(toy, config, stream=True), region=region, root=tmp_path)
    assert other.directory != database.directory  # other points (no SN): another entry


def test_cache_is_not_written_inside_an_artifact(toy, tmp_path, monkeypatch):
    monkeypatch.delenv("DALI_CACHE_DIR", raising=False)
    assert cache_root(toy) == toy.parent / ".dali-cache"
    nested = tmp_path / "artifact" / "inner"
    nested.mkdir(parents=True)
    (tmp_path / "artifact" / "manifest.json").write_text('{"stage": "ppcg", "dali_version": "0"}')
    assert cache_root(nested / "set") == tmp_path / ".dali-cache"
    monkeypatch.setenv("DALI_CACHE_DIR", str(tmp_path / "elsewhere"))
    assert cache_root(toy) == tmp_path / "elsewhere"


def streamed_set(toy, config, cache):
    data = load_labeled(toy, config, stream=True)
    data.database = cached_database(data, region=detection_region(config), root=cache)
    return data


def test_loader_batches_do_not_depend_on_the_number_of_workers(toy, config, tmp_path):
    data = streamed_set(toy, config, tmp_path)
    samples = TrainingSamples([data], [Augmentation()], seed=4)
    runs = []
    for workers in (0, 1, 2):
        batches = StepBatches([len(data)], (1,), 2, range(2), seed=4, start=1, stop=6)
        runs.append(list(training_loader(samples, batches, config, workers, pin_memory=False)))
    assert len(runs[0]) == 5
    for other in runs[1:]:
        for a, b in zip(runs[0], other, strict=True):
            assert torch.equal(a.points, b.points) and torch.equal(a.batch_index, b.batch_index)
            assert torch.equal(a.targets.heatmap, b.targets.heatmap)
            assert torch.equal(a.targets.regression, b.targets.regression)
            assert same_arrays(a.frame_points, b.frame_points)
    # a rank's share of the global batch is its part of the serial batch
    rank1 = StepBatches([len(data)], (1,), 2, range(1, 2), seed=4, start=1, stop=6)
    serial = StepBatches([len(data)], (1,), 2, range(2), seed=4, start=1, stop=6)
    assert [keys[1:] for keys in serial] == list(rank1)


def train_weights(data, workers: int) -> dict:
    torch.manual_seed(0)
    net = PillarCenterNet(DetectorConfig.from_dict(SMALL))
    settings = TrainSettings(epochs=1, batch_size=2, seed=1, threads=1, loader_workers=workers)
    train(net, [data], [Augmentation()], settings, progress=False)
    return net.state_dict()


def test_training_on_streamed_frames_equals_training_in_memory(toy, config, tmp_path):
    memory = load_labeled(toy, config)
    memory.database = ObjectDatabase.build(
        memory.points, memory.boxes, region=detection_region(config)
    )
    reference = train_weights(memory, workers=0)
    for workers in (0, 2):
        weights = train_weights(streamed_set(toy, config, tmp_path), workers)
        assert all(torch.equal(reference[k], weights[k]) for k in reference), workers


def test_loader_workers_default_to_a_spare_core_on_the_cpu_and_to_the_spare_cores_on_a_gpu(
    monkeypatch,
):
    """On the CPU the training step computes on its threads: one worker when they leave a core
    spare, else the input pipeline in process; on a GPU the spare cores (one kept for the step)
    feed it."""
    from dali_cli.detector import loader

    monkeypatch.setattr("dali_cli.runtime.cores.available_cores", lambda: 6)
    assert loader.default_loader_workers(1, "cpu") == 0
    assert loader.default_loader_workers(1, "cpu", threads=6) == 0
    assert loader.default_loader_workers(1, "cpu", threads=1) == 1
    assert loader.default_loader_workers(2, "cpu", threads=3) == 0  # two ranks: 3 cores each
    assert loader.default_loader_workers(1, "cuda") == 5
    assert loader.default_loader_workers(2, "cuda") == 2  # two ranks share the six cores
    monkeypatch.setattr("dali_cli.runtime.cores.available_cores", lambda: 64)
    assert loader.default_loader_workers(1, "cuda") == loader.MAX_DEFAULT_WORKERS
    monkeypatch.setattr("dali_cli.runtime.cores.available_cores", lambda: 2)
    assert loader.default_loader_workers(1, "cpu", threads=1) == 1  # the shipped chain's run


def test_prepared_frames_are_bounded_least_recently_used_first_out_and_read_only():
    from dali_cli.detector.data import PreparedFrames

    kept = PreparedFrames(max_bytes=3 * 400)
    arrays = {i: np.full((25, 4), i, np.float32) for i in range(5)}  # 400 bytes each
    for i in (0, 1, 2):
        kept.put(("a", i), arrays[i])
    assert kept.get(("a", 0)) is arrays[0]  # 0 is now the most recent: 1 goes first
    kept.put(("a", 3), arrays[3])
    assert kept.get(("a", 1)) is None and kept.get(("a", 2)) is arrays[2] and kept.bytes == 1200
    assert not arrays[3].flags.writeable
    with pytest.raises(ValueError):
        arrays[3][0, 0] = 1.0  # a sample cannot change the frame every later sample reads
    big = np.zeros((400, 4), np.float32)
    assert kept.put(("a", 9), big) is big and kept.get(("a", 9)) is None and kept.bytes == 1200


@pytest.mark.parametrize("limit_bytes", ["0", str(1 << 30)])
def test_streamed_frames_are_prepared_once_per_process_within_the_limit(
    toy, config, monkeypatch, limit_bytes
):
    from dali_cli.detector import data

    monkeypatch.setenv("DALI_FRAME_CACHE_BYTES", limit_bytes)
    monkeypatch.setattr(data, "_PREPARED", None)
    memory = load_labeled(toy, config)
    streamed = load_labeled(toy, config, stream=True)
    first, again = streamed.points[2], streamed.points[2]
    assert (first is again) == (limit_bytes != "0")
    assert np.array_equal(first, memory.points[2]) and np.array_equal(again, memory.points[2])
    scaled = scale_about_ground(streamed, 0.9).points[2]  # another reader: not the cached frame
    assert np.array_equal(scaled, scale_about_ground(memory, 0.9).points[2])
    assert data.prepared_frames().bytes <= int(limit_bytes)
