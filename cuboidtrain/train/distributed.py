"""Many trainers under `torchrun` (DDP): one process per rank, every rank reading one spool.

DDP's collectives hang when one rank takes a step and another does not, so the
ranks agree on everything that decides how many steps run:

* the listing: rank 0 lists the spool and broadcasts the names; every rank shuffles
  them with the same seed and takes its strided share of each global batch
  (`cuboidtrain.data.sampler.rank_batches`), so the shares are disjoint and together cover the epoch;
* each batch's fate: a listing gone stale, or a rank left with too few samples
  (a sample vanished on one rank only), is decided on counts summed over ranks;
* stopping (SIGTERM, Ctrl-C, --max-minutes): a rank stops when any rank asks.

Only rank 0 writes (checkpoints, metrics, status.json, the dashboard); other ranks
log only warnings. A single process is a world of one: every method below then
returns its input untouched, so that path runs exactly as without this module.
"""
from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import nn

from cuboidtrain.train.losses import phase_losses

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Ranks:
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")  # where collectives' tensors live (CUDA for NCCL)

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1

    def broadcast(self, obj):
        """Rank 0's `obj` on every rank."""
        if not self.distributed:
            return obj
        box = [obj if self.main else None]
        dist.broadcast_object_list(box, src=0, device=self.device)
        return box[0]

    def sum(self, values: list[float]) -> list[float]:
        """Element-wise sums over ranks."""
        if not self.distributed:
            return values
        t = torch.tensor(values, dtype=torch.float64, device=self.device)
        dist.all_reduce(t, op=dist.ReduceOp.SUM)
        return t.tolist()

    def any(self, flag: bool) -> bool:
        """True on every rank when it is True on any rank."""
        if not self.distributed:
            return flag
        return self.sum([float(bool(flag))])[0] > 0

    def gather(self, obj) -> list:
        """Every rank's `obj`, in rank order, on every rank."""
        if not self.distributed:
            return [obj]
        out = [None] * self.world
        dist.all_gather_object(out, obj)
        return out


def from_environment(device: torch.device) -> tuple[Ranks, torch.device]:
    """The ranks torchrun describes in WORLD_SIZE/RANK/LOCAL_RANK, with the process group
    started, and this rank's device; a plain process is a world of one."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Ranks(), device
    rank, local_rank = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if device.type == "cuda":
        device = torch.device("cuda", local_rank)  # one GPU per rank
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return Ranks(rank, world, local_rank, device), device


def shutdown(ranks: Ranks, together: bool = False) -> None:
    """Ends the process group. `together` (every rank came to the end of its run): first wait for
    the others, so that no rank tears its connections down while another still talks (one run in
    about 20 of tests/test_ddp.py aborted a rank at exit, after its last step, without it); after
    a failure a rank leaves at once, as the others may never come."""
    if ranks.distributed and dist.is_initialized():
        if together:
            dist.barrier()
        dist.destroy_process_group()


class PhaseLosses(nn.Module):
    """`phase_losses` as one module call: phase 1 runs R, S and T separately, and DDP
    synchronises gradients only for what runs inside its wrapper's forward."""

    def __init__(self, model: nn.Module, phase: str, ratio_weight: float):
        super().__init__()
        self.model, self.phase, self.ratio_weight = model, phase, ratio_weight

    def forward(self, x: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return phase_losses(self.model, x, self.phase, self.ratio_weight)


def wrap(model: nn.Module, phase: str, ratio_weight: float, ranks: Ranks) -> nn.Module | None:
    """The DDP module that trains `model` on every rank; None in a single process.

    Checkpoints keep saving `model` itself, so their keys carry no `module.` prefix and
    load in single-process eval and infer."""
    if not ranks.distributed:
        return None
    ids = [ranks.device.index] if ranks.device.type == "cuda" else None
    return nn.parallel.DistributedDataParallel(PhaseLosses(model, phase, ratio_weight), device_ids=ids)


def weights_digest(model: nn.Module) -> str:
    """A hash of every parameter: equal on every rank while the replicas agree. (Not the
    buffers: BatchNorm's running statistics are rank 0's only at each forward's start, when
    DDP broadcasts them, and rank 0's are what the checkpoint keeps.)"""
    h = hashlib.sha256()
    for key, value in model.named_parameters():
        h.update(key.encode())
        h.update(value.detach().cpu().contiguous().view(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()[:16]
