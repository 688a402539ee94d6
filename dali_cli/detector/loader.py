"""The training input pipeline: which frames each optimizer step trains on (`StepBatches`, the
global-batch sampler, a rank's share of it under torchrun), a torch Dataset that makes one
augmented sample of a frame (`TrainingSamples`), and the batch it becomes (`collate`: points,
their frame index, the detection targets), built in DataLoader worker processes.

Every random draw of a sample is seeded by (run seed, step, the frame's position in the global
batch), never by the worker or the rank, so the batches are the same with any number of
workers (0: built in the training process) and any number of ranks.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from dali_cli.detector.data import augmented_sample
from dali_cli.detector.targets import Targets, build_targets

MAX_DEFAULT_WORKERS = 8


def default_loader_workers(
    local_processes: int = 1, device_type: str = "cuda", threads: int | None = None
) -> int:
    """Loader workers per training process when not given. On a GPU: one less than its share of
    the available cores (the training process keeps one), at most MAX_DEFAULT_WORKERS. On the
    CPU: one when the step's torch `threads` leave a core of the process's share spare (the
    shipped chain's --threads 1 on 2 cores: the batches are made there while the step runs,
    docs/detector.md "Where a training step's time goes"), else none: the step computes on every
    core, and a worker would take cores from it (measured ~2x slower on a 2-core machine,
    docs/scale-out-measurements.md)."""
    from dali_cli.runtime.cores import available_cores

    share = available_cores() // max(1, local_processes)
    if device_type != "cuda":
        return 1 if threads is not None and threads < share else 0
    return max(0, min(MAX_DEFAULT_WORKERS, share - 1))


def interleave(mix: tuple[int, ...]) -> list[int]:
    """Data set of each step in one cycle: (1, 1) -> [0, 1]; (2, 1) -> [0, 1, 0]."""
    counts, pattern = list(mix), []
    total = sum(counts)
    taken = [0] * len(counts)
    for step in range(total):  # spread each set evenly over the cycle
        d = max(range(len(counts)), key=lambda i: counts[i] * (step + 1) / total - taken[i])
        taken[d] += 1
        pattern.append(d)
    return pattern


def batch_indices(
    size: int, batch_number: int, batch_size: int, seed: int, dataset: int
) -> np.ndarray:
    """Frame indices of the `batch_number`-th batch of a set: a fresh permutation per pass."""
    positions = batch_number * batch_size + np.arange(batch_size)
    passes = positions // size
    out = np.empty(batch_size, np.int64)
    for p in np.unique(passes):  # at most two passes per batch
        order = np.random.default_rng([seed, dataset, int(p)]).permutation(size)
        out[passes == p] = order[positions[passes == p] % size]
    return out


def step_frames(
    sizes: list[int], pattern: list[int], step: int, global_batch: int, seed: int
) -> tuple[int, np.ndarray]:
    """(data set, frame indices (global_batch,)) of optimizer step `step`: the set the mix's
    interleaving gives it, and that set's next batch of its per-pass permutations."""
    d = pattern[step % len(pattern)]
    cycles, within = divmod(step, len(pattern))
    batch_number = cycles * pattern.count(d) + pattern[:within].count(d)
    return d, batch_indices(sizes[d], batch_number, global_batch, seed, d)


class StepBatches(Sampler):
    """Keys (data set, frame index, step, position in the global batch) of this rank's frames,
    one list per optimizer step from `start` to `stop` (None: without end). `positions` are the
    rank's positions in the global batch (distributed.rank_slice): every rank walks the same
    permutation and takes its part of each global batch."""

    def __init__(
        self, sizes: list[int], mix: tuple[int, ...], global_batch: int, positions, seed: int,
        start: int = 0, stop: int | None = None,
    ):  # fmt: skip
        self.sizes, self.pattern = list(sizes), interleave(mix)
        self.global_batch, self.positions = global_batch, list(positions)
        self.seed, self.start, self.stop = seed, start, stop

    def __iter__(self):
        steps = itertools.count(self.start) if self.stop is None else range(self.start, self.stop)
        for step in steps:
            d, indices = step_frames(self.sizes, self.pattern, step, self.global_batch, self.seed)
            yield [(d, int(indices[j]), step, j) for j in self.positions]

    def __len__(self) -> int:
        if self.stop is None:
            raise TypeError("a wall-clock budget has no number of steps")
        return max(0, self.stop - self.start)


class TrainingSamples(Dataset):
    """Item (d, index, step, j): (d, data.Sample) of frame `index` of data set d augmented with
    the draws of numpy Generator (seed, step, j)."""

    def __init__(self, datasets: list, augmentations: list, seed: int):
        self.datasets, self.augmentations, self.seed = datasets, augmentations, seed

    def __len__(self) -> int:
        return sum(len(d) for d in self.datasets)

    def __getitem__(self, key: tuple[int, int, int, int]):
        d, index, step, j = key
        rng = np.random.default_rng([self.seed, step, j])
        return d, augmented_sample(self.datasets[d], index, rng, self.augmentations[d])


@dataclass
class Batch:
    """One rank's batch of an optimizer step: its data set, the B frames' points (P, 4) float32
    with their frame index (P,) int64 in the batch, the detection targets, and each frame's
    points (n_b, 4) as numpy (the refiner's input)."""

    dataset: int
    points: torch.Tensor
    batch_index: torch.Tensor
    targets: Targets
    frame_points: list[np.ndarray]

    def __len__(self) -> int:
        return len(self.frame_points)

    def pin_memory(self) -> Batch:
        """The tensors in page-locked memory (faster, asynchronous copies to a GPU)."""
        t = self.targets
        targets = Targets(
            t.heatmap.pin_memory(), t.index.pin_memory(), t.mask.pin_memory(),
            t.regression.pin_memory(), t.boxes, t.weight.pin_memory(), t.objects,
            None if t.direction is None else t.direction.pin_memory(),
        )  # fmt: skip
        points, index = self.points.pin_memory(), self.batch_index.pin_memory()
        return Batch(self.dataset, points, index, targets, self.frame_points)


def collate(items: list, config) -> Batch:
    """The Batch of (d, data.Sample) items (one data set) for a detector of `config`."""
    dataset = items[0][0]
    samples = [sample for _, sample in items]
    points = torch.from_numpy(np.concatenate([s.points for s in samples]))  # (P, 4)
    batch_index = torch.from_numpy(
        np.repeat(np.arange(len(samples)), [len(s.points) for s in samples])
    )
    targets = build_targets([s.boxes for s in samples], config)
    return Batch(dataset, points, batch_index, targets, [s.points for s in samples])


def worker_init(_worker_id: int) -> None:
    """A loader worker computes with one thread: the cores are the workers'."""
    torch.set_num_threads(1)


def start_loader(loader: DataLoader):
    """An iterator over `loader`'s batches, made with the CPU as the default device (the loader
    makes a CPU tensor for its seed, whatever device a caller made the default). Before its
    workers fork, the heap the loading passes freed goes back to the system, so that the workers
    do not share (and count) it."""
    if loader.num_workers:
        release_free_heap()
    with torch.device("cpu"):
        return iter(loader)


def stop_loader(batches) -> None:
    """Stop the worker processes of a loader iterator now, not when it is collected (a
    traceback that holds it would keep them alive)."""
    shutdown = getattr(batches, "_shutdown_workers", None)
    if shutdown is not None:
        shutdown()


def release_free_heap() -> None:
    """glibc's malloc_trim(0): return freed heap pages to the system (a no-op elsewhere)."""
    import ctypes
    import ctypes.util

    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def training_loader(
    samples: TrainingSamples, batches: StepBatches, config, workers: int, pin_memory: bool
) -> DataLoader:
    """The DataLoader of `batches`' steps: samples made and collated in `workers` processes (0:
    in this one), each prefetching two steps ahead, in step order. Its own torch generator
    (the samples draw from numpy Generators seeded per frame; the loader's seed for its workers
    does not consume the global torch stream, so training draws the same with or without it)."""
    generator = torch.Generator(device="cpu")
    generator.manual_seed(samples.seed)
    return DataLoader(
        samples,
        generator=generator,
        batch_sampler=batches,
        collate_fn=functools.partial(collate, config=config),
        num_workers=workers,
        pin_memory=pin_memory,
        worker_init_fn=worker_init if workers else None,
        prefetch_factor=2 if workers else None,
    )
