"""Data-parallel training under torchrun (torch.distributed): the one module that knows about
process groups. The serial path (world size 1) is the reference: everything here reduces to
the identity there, and a run of W ranks with b frames each takes exactly the step a single
process takes on the W * b frames as one batch.

What makes the two equal:
- the global batch: the serial sampler draws W * b frame indices per step; rank r trains on
  positions [r * b, (r + 1) * b) of them (an epoch is every frame once across all ranks), and
  every random draw of a frame (augmentation, refiner jitter) is seeded by the run seed, the step
  and the frame's position in the global batch, not by the rank;
- global-batch means: a loss normalised by a count (positive cells, box cells, proposals) divides
  by that count summed over the ranks and over W (`global_normalizer`); DDP then averages the
  ranks' gradients, which gives the gradient of the serial batch's loss;
- batch statistics over the global batch: batch norm layers are synchronised (torch's
  SyncBatchNorm on CUDA; on the CPU, where torch's needs a GPU, `SyncBatchNormCPU` all-reduces
  the sums through torch.distributed.nn's differentiable all_reduce).

Rank 0 alone writes (the artifact, resume states, the log); the stage runner asks every rank
whether it finished before rank 0 commits (`all_succeeded`).
"""

from __future__ import annotations

import inspect
import os
import warnings
from dataclasses import dataclass, replace
from datetime import timedelta

import torch
import torch.distributed as dist
from torch import nn

from dali_cli.runtime.errors import StageError

DEFAULT_TIMEOUT_S = 1800.0  # a collective waiting longer than this fails the run


@dataclass(frozen=True)
class World:
    """This process's place in a distributed run (torchrun's RANK, WORLD_SIZE, LOCAL_RANK,
    LOCAL_WORLD_SIZE). The default is a single process."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0
    local_size: int = 1
    backend: str | None = None
    device: torch.device | None = None  # where this rank's collectives' tensors live

    @property
    def distributed(self) -> bool:
        return self.size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


SINGLE = World()


def launched(environ=None) -> World:
    """The World torchrun (or srun + torchrun) described in the environment; SINGLE without one.
    Does not join the process group (`join` does)."""
    environ = os.environ if environ is None else environ
    size = int(environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return SINGLE
    try:
        rank = int(environ["RANK"])
    except KeyError:
        raise StageError(
            f"WORLD_SIZE={size} but RANK is not set: start distributed training with torchrun "
            "(torchrun --nproc-per-node N $(which dali) pretrain ...)"
        ) from None
    local_rank = int(environ.get("LOCAL_RANK", rank))
    local_size = int(environ.get("LOCAL_WORLD_SIZE", size))
    return World(rank=rank, size=size, local_rank=local_rank, local_size=local_size)


def join(world: World, device: torch.device, timeout_s: float = DEFAULT_TIMEOUT_S) -> World:
    """Join the process group of `world` (gloo on the CPU, nccl on CUDA); returns the World with
    its backend and device. A single process joins nothing."""
    if not world.distributed:
        return replace(world, device=device)
    backend = "nccl" if device.type == "cuda" else "gloo"
    stop_on_sigterm()
    if not dist.is_initialized():
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group(backend, timeout=timedelta(seconds=timeout_s))
    if dist.get_world_size() != world.size or dist.get_rank() != world.rank:
        raise StageError(
            f"process group is rank {dist.get_rank()} of {dist.get_world_size()}, the environment "
            f"says {world.rank} of {world.size}"
        )
    return replace(world, backend=dist.get_backend(), device=device)


def stop_on_sigterm() -> None:
    """SIGTERM (what torchrun sends the other ranks when one fails) raises SystemExit, so the
    stage runner's cleanup removes the temporary output instead of the process dying in place."""
    import signal

    def stop(signum, frame):
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)


def leave() -> None:
    """Leave the process group (at the end of a distributed stage)."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def active() -> bool:
    """True inside a process group of more than one rank."""
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def global_normalizer(count: torch.Tensor, minimum: float) -> torch.Tensor:
    """The denominator that turns a rank's summed loss into its share of the global-batch mean.

    count: this rank's () count (positive cells, weights, proposals). Serially: count clamped at
    `minimum`. Under DDP: the count summed over the ranks, clamped, over the world size, so that
    DDP's average of the ranks' gradients is the gradient of sum(all losses) / sum(all counts).
    The count carries no gradient (an all_reduce of a detached copy)."""
    if not active():
        return count.clamp(min=minimum)
    total = count.detach().clone()
    dist.all_reduce(total)
    return total.clamp(min=minimum) / dist.get_world_size()


def mean_over_ranks(values: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The ranks' () loss terms averaged over the ranks (for the log: with global_normalizer,
    the mean of the ranks' losses is the global batch's loss)."""
    if not active() or not values:
        return values
    names = list(values)
    stacked = torch.stack([values[n].detach().float() for n in names])
    dist.all_reduce(stacked)
    stacked /= dist.get_world_size()
    return dict(zip(names, stacked, strict=True))


def rank_slice(world: World, per_rank: int) -> range:
    """Positions in the global batch (W * per_rank frames) this rank trains on."""
    return range(world.rank * per_rank, (world.rank + 1) * per_rank)


class SyncBatchNormCPU(nn.modules.batchnorm._BatchNorm):
    """Batch norm whose training statistics are those of the global batch: per-channel sums of
    x and x^2 and the element count are summed over the ranks with torch.distributed.nn's
    all_reduce (differentiable: its backward sums the gradients), so the output and the
    gradients equal those of one process holding every rank's frames. For gloo on the CPU
    (torch's SyncBatchNorm runs on GPUs only). Input (N, C, *) float; statistics in float64."""

    def _check_input_dim(self, input):
        if input.dim() < 2:
            raise ValueError(f"expected at least 2D input (got {input.dim()}D input)")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (self.training and active()):
            return super().forward(x)
        from torch.distributed.nn.functional import all_reduce

        channels = x.shape[1]
        dims = [0, *range(2, x.dim())]
        wide = x.double()
        count = torch.full((1,), x.numel() / channels, dtype=torch.float64, device=x.device)
        local = torch.cat([wide.sum(dims), (wide * wide).sum(dims), count])  # (2C + 1,)
        with warnings.catch_warnings():  # deprecated in torch 2.13, its successor is private
            warnings.simplefilter("ignore", FutureWarning)
            total = all_reduce(local)
        n = total[-1]
        mean = total[:channels] / n  # (C,)
        var = (total[channels : 2 * channels] / n - mean * mean).clamp(min=0)  # biased
        shape = (1, channels) + (1,) * (x.dim() - 2)
        scale = torch.rsqrt(var + self.eps)
        y = ((wide - mean.view(shape)) * scale.view(shape)).to(x.dtype)
        if self.affine:
            y = y * self.weight.view(shape) + self.bias.view(shape)
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                m = (
                    self.momentum
                    if self.momentum is not None
                    else 1.0 / float(self.num_batches_tracked)
                )
                unbiased = var * n / (n - 1).clamp(min=1)
                self.running_mean.mul_(1 - m).add_(m * mean.to(self.running_mean.dtype))
                self.running_var.mul_(1 - m).add_(m * unbiased.to(self.running_var.dtype))
        return y


def convert_batch_norm(module: nn.Module, device: torch.device) -> nn.Module:
    """`module` with every BatchNorm*d replaced by its synchronised form (weights and running
    statistics kept): torch's SyncBatchNorm on CUDA, SyncBatchNormCPU elsewhere."""
    if device.type == "cuda":
        return nn.SyncBatchNorm.convert_sync_batchnorm(module)
    if isinstance(module, nn.modules.batchnorm._BatchNorm) and not isinstance(
        module, SyncBatchNormCPU
    ):
        synced = SyncBatchNormCPU(
            module.num_features, module.eps, module.momentum, module.affine,
            module.track_running_stats,
        )  # fmt: skip
        synced.load_state_dict(module.state_dict())
        synced.train(module.training)
        return synced
    for name, child in module.named_children():
        module.add_module(name, convert_batch_norm(child, device))
    return module


def wrap(net: nn.Module, world: World) -> nn.Module:
    """`net` for training on `world`: itself serially; under DDP its batch norms synchronised and
    the module wrapped in DistributedDataParallel (which broadcasts rank 0's weights now and
    averages the gradients in backward). Buffers are not broadcast each step: synchronised batch
    norm keeps them equal on every rank. The synchronised layers keep the state-dict keys of
    plain batch norm, so the saved weights load into the serial model."""
    if not world.distributed:
        return net
    from torch.nn.parallel import DistributedDataParallel

    convert_batch_norm(net, world.device)
    device_ids = [world.device.index] if world.device.type == "cuda" else None
    accepted = inspect.signature(DistributedDataParallel.__init__).parameters
    no_sync = (  # torch 2.13 renamed the switch (both still sync the buffers at construction)
        {"forward_sync_buffers": False}
        if "forward_sync_buffers" in accepted
        else {"broadcast_buffers": False}
    )
    return DistributedDataParallel(net, device_ids=device_ids, **no_sync)


def broadcast_object(value, world: World):
    """Rank 0's `value` on every rank (pickled; for small things: decisions, resume states)."""
    if not world.distributed:
        return value
    box = [value if world.is_main else None]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def broadcast_float(value: float, world: World) -> float:
    """Rank 0's float on every rank (e.g. the elapsed time that a --minutes budget runs on)."""
    if not world.distributed:
        return value
    tensor = torch.tensor([value], dtype=torch.float64, device=world.device)
    dist.broadcast(tensor, src=0)
    return float(tensor.item())


def all_succeeded(world: World) -> None:
    """A barrier every rank reaches only after it finished its work without an error. A rank
    that failed never arrives: its process has exited, and the collective raises on the others
    (gloo: connection closed; torchrun also stops the group), so rank 0 never commits."""
    if not world.distributed:
        return
    done = torch.ones(1, device=world.device)
    dist.all_reduce(done)
    if int(done.item()) != world.size:
        raise StageError(f"only {int(done.item())} of {world.size} ranks finished: nothing written")
