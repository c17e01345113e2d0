"""Training on several processes (one per GPU) with PyTorch's DistributedDataParallel: started by
``torchrun``, which sets ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK`` and the rendezvous address for
each process. Without those variables every function here is the single process's no-op.

Each rank trains on its own shards of a pack (`learn.shards.ShardScenes`), gradients are averaged
across ranks at every step, every rank validates on the whole validation split and all take rank
0's figures (BatchNorm's running statistics differ a little between ranks), so all agree on the
best epoch, the schedule and early stopping; rank 0 alone writes files and logs progress. Every
rank reads the resumable checkpoint rank 0 wrote: the output folder must be on a filesystem all
of the job's nodes see.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import torch
from torch import nn

from .. import PsdError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Ranks:
    """This process's place in a multi-process training: `rank` of `world`, `local` on its node."""

    rank: int = 0
    world: int = 1
    local: int = 0

    @property
    def main(self) -> bool:
        """The process that writes the files and logs progress."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1


def ranks_from_env(env: dict[str, str] | os._Environ = os.environ) -> Ranks:
    """The ranks torchrun gave this process (RANK, WORLD_SIZE, LOCAL_RANK), else a single process."""
    try:
        world = int(env.get("WORLD_SIZE", "1"))
        rank = int(env.get("RANK", "0"))
        local = int(env.get("LOCAL_RANK", str(rank)))
    except ValueError:
        raise PsdError("RANK, WORLD_SIZE and LOCAL_RANK must be whole numbers (torchrun sets them)") from None
    if world < 1 or not 0 <= rank < world or local < 0:
        raise PsdError(f"RANK {rank} of WORLD_SIZE {world} (LOCAL_RANK {local}): not a rank of that world")
    return Ranks(rank, world, local)


def start(ranks: Ranks, device: torch.device) -> torch.device:
    """Join the process group (NCCL between GPUs, Gloo on CPUs) and return this rank's device:
    its own GPU (LOCAL_RANK) where `device` is a GPU, else the CPU."""
    if not ranks.distributed:
        return device
    import torch.distributed as dist

    if device.type == "cuda":
        if ranks.local >= torch.cuda.device_count():
            raise PsdError(f"LOCAL_RANK {ranks.local} but {torch.cuda.device_count()} GPUs here: give torchrun "
                           "--nproc-per-node at most the node's GPUs")
        device = torch.device("cuda", ranks.local)
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    if ranks.main:
        logger.info(f"distributed training: {ranks.world} processes ({dist.get_backend()}), this one on {device}")
    return device


def stop(ranks: Ranks) -> None:
    if ranks.distributed:
        import torch.distributed as dist

        if dist.is_initialized():
            dist.barrier()
            dist.destroy_process_group()


def wrap(module: nn.Module, ranks: Ranks, device: torch.device, unused: bool = False) -> nn.Module:
    """`module` as DistributedDataParallel (gradients averaged across ranks in its backward), or
    itself in a single process. The wrapper trains; the module inside is what is saved. `unused`:
    some parameters get no gradient in a step (DDP then looks for them each step)."""
    if not ranks.distributed:
        return module
    from torch.nn.parallel import DistributedDataParallel

    return DistributedDataParallel(module, device_ids=[device.index] if device.type == "cuda" else None,
                                   find_unused_parameters=unused)


def agree(value, ranks: Ranks):
    """Rank 0's `value` on every rank (e.g. a precision chosen by timing, which could differ)."""
    if not ranks.distributed:
        return value
    import torch.distributed as dist

    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def barrier(ranks: Ranks) -> None:
    """Wait until every rank is here (e.g. before the others read a file rank 0 wrote)."""
    if ranks.distributed:
        import torch.distributed as dist

        dist.barrier()
