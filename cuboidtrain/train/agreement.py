"""What the ranks agree on after each batch: its skips, whether it is stale or too small, its losses, whether the step diverged."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from cuboidtrain.data.loader import LoaderBatch
from cuboidtrain.models.checkpoint import non_finite_weights
from cuboidtrain.train.distributed import Ranks


@dataclass(frozen=True)
class BatchFacts:
    """A batch's skip counts summed over ranks, and whether any rank holds too few samples to step on."""

    skipped: dict[str, int]
    too_small: bool


@dataclass(frozen=True)
class StepLosses:
    """A step's losses averaged over ranks (the global batch's), and the samples all ranks stepped on."""

    losses: dict[str, float]
    samples: int


def stale(skipped: dict, batch_size: int) -> bool:
    """More than half of the (global) batch vanished: the epoch's listing no longer matches the spool."""
    return 2 * skipped["vanished"] > batch_size


def batch_facts(ranks: Ranks, batch: LoaderBatch, least: int = 2) -> BatchFacts:
    """The batch's skip counts summed over ranks, and whether any rank holds fewer than `least`
    samples, too few to step on (`least_batch`): every rank then skips it, or DDP would hang."""
    if not ranks.distributed:
        return BatchFacts(batch.skipped, len(batch.names) < least)
    sums = ranks.sum([*batch.skipped.values(), float(len(batch.names) < least)])
    return BatchFacts(dict(zip(batch.skipped, (int(n) for n in sums))), sums[-1] > 0)


def global_losses(ranks: Ranks, losses: dict[str, float], samples: int) -> StepLosses:
    """The losses averaged over ranks (the global batch's) and the samples all ranks stepped on."""
    if not ranks.distributed:
        return StepLosses(losses, samples)
    sums = ranks.sum([*losses.values(), samples])
    return StepLosses({k: v / ranks.world for k, v in zip(losses, sums)}, int(sums[-1]))


def divergence(losses: dict[str, float], model: torch.nn.Module) -> str | None:
    """What is NaN or Infinity after a step, its losses or its weights; None when nothing is.
    One reduction over the weights (a NaN or Infinity anywhere makes the sum non-finite), one
    sync. Every rank finds the same: the losses are global_losses', the weights DDP's."""
    bad = [f"{name} is {value}" for name, value in losses.items() if not math.isfinite(value)]
    if bad:
        return ", ".join(bad)
    with torch.no_grad():
        tensors = [t for t in (*model.parameters(), *model.buffers()) if t.is_floating_point()]
        if math.isfinite(torch.stack([t.float().sum() for t in tensors]).sum().item()):
            return None
    count, total = non_finite_weights(model.state_dict())
    return f"{count} of {total} weights are NaN or Infinity after it"
