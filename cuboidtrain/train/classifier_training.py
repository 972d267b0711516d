"""Training the shape classifier (`cuboidtrain.models.classifier`) from a box spool and a twobox spool.

Every sample's noisy mask (one an occluder hid whole left out) is framed as `infer` frames it
(`cuboidtrain.fit.shape_call.classifier_input`) and held in memory: 120,000 masks of 64 px are 2 GB
as float32. Batches are drawn at random, each mask mirrored at random (a mirrored building is the
same class), by AdamW under a cosine over the minutes or steps given; binary cross-entropy on the
twobox logit. One thread by default: it trains beside the other daemons.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from cuboidtrain.fit.shape_call import classifier_input
from cuboidtrain.models.classifier import ShapeClassifier, load_classifier
from cuboidtrain.models.device import resolve_device
from shared.errors import UsageError
from shared.sample import decode
from shared.spool import enumerate_spool, read_sample_bytes

log = logging.getLogger(__name__)

LR, FINAL_LR, WEIGHT_DECAY = 2e-3, 1e-5, 1e-4


@dataclass(frozen=True)
class TrainedClassifier:
    net: ShapeClassifier  # on the CPU, in eval mode
    steps: int
    batch_size: int
    masks: dict[str, int]  # class -> framed masks it trained on
    hidden: int  # masks an occluder hid whole, left out
    wall_time_s: float
    device: str = "cpu"
    init: dict | None = None  # the card of the classifier it started from, if not from random weights
    lr: float = LR  # the cosine's peak learning rate

    def card(self, spools: dict[str, Path], scenes: list[str], commit: str | None, recipe: str | None) -> dict:
        """The model file's card: how it was trained, in the model cards' fields (`cuboidtrain models`)."""
        return {"shape": "box|twobox", "arch": "classifier", "size": 64, "grey_input": True, "scenes": scenes,
                "steps": self.steps, "batch_size": self.batch_size, "samples_seen": self.steps * self.batch_size,
                "masks": self.masks, "hidden_masks": self.hidden, "wall_time_s": round(self.wall_time_s, 1), "device": self.device,
                "spools": {shape: str(path) for shape, path in spools.items()}, "commit": commit, "recipe": recipe,
                "init": self.init, "lr": self.lr}


def framed_masks(spool: Path) -> tuple[np.ndarray, int]:
    """(M, 64, 64) float32: the spool's noisy masks framed as `infer` frames them, and how many were empty."""
    names = enumerate_spool(spool)
    if not names:
        raise UsageError(f"spool {spool}: no samples to train the shape classifier on")
    masks = (decode(read_sample_bytes(spool, name)).noisy for name in names)
    framed = [classifier_input(mask) for mask in masks if mask.any()]
    if not framed:
        raise UsageError(f"spool {spool}: every sample's mask is empty (hidden whole): nothing to train on")
    return np.stack(framed), len(names) - len(framed)


def train_classifier(spools: dict[str, Path], minutes: float | None = None, steps: int | None = None,
                     batch_size: int = 128, seed: int = 0, device: str = "cpu", init: Path | None = None,
                     lr: float | None = None) -> TrainedClassifier:
    """The classifier trained on `spools` ({"box": DIR, "twobox": DIR}) for `minutes` or `steps`
    (whichever ends first; at least one given), the learning rate a cosine over that span, from random
    weights or from the classifier file `init` (training on: its card is kept in the new one's; a peak `lr`
    below LR keeps more of what it learnt). On a
    GPU (`device`) the framed masks are held there whole (120,000 are 2 GB) and batches drawn there."""
    if minutes is None and steps is None:
        raise UsageError("the shape classifier's training needs --minutes or --steps")
    lr = LR if lr is None else lr
    if not lr > FINAL_LR:  # checked before the spools are read (minutes, for a large one)
        raise UsageError(f"the shape classifier's learning rate {lr!r}: expected more than its final {FINAL_LR}")
    where = resolve_device(device)
    read = {shape: framed_masks(spools[shape]) for shape in ("box", "twobox")}
    x = torch.from_numpy(np.concatenate([read["box"][0], read["twobox"][0]]))[:, None].to(where)
    y = torch.cat([torch.zeros(len(read["box"][0])), torch.ones(len(read["twobox"][0]))]).to(where)
    torch.manual_seed(seed)
    net, init_card = load_classifier(init, folded=False) if init is not None else (ShapeClassifier(), None)
    net = net.train().to(where)
    optimizer = torch.optim.AdamW(net.parameters(), lr, weight_decay=WEIGHT_DECAY)
    start, step = time.monotonic(), 0
    while (done := progress(start, step, minutes, steps)) < 1.0:
        for group in optimizer.param_groups:
            group["lr"] = FINAL_LR + (lr - FINAL_LR) * 0.5 * (1 + math.cos(math.pi * done))
        # drawn on the CPU's generator wherever the masks are: the same batches for a seed on any device
        chosen = torch.randint(len(x), (batch_size,)).to(where)
        flip = (torch.rand(batch_size)[:, None, None, None] < 0.5).to(where)
        logits = net(torch.where(flip, x[chosen].flip(-1), x[chosen]))
        loss = nn.functional.binary_cross_entropy_with_logits(logits, y[chosen])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        step += 1
        if step % 500 == 0:
            log.info("shape classifier: step %d, loss %.3f, %.1f min", step, loss.item(), (time.monotonic() - start) / 60)
    return TrainedClassifier(net.cpu().eval(), step, batch_size, {k: len(v[0]) for k, v in read.items()},
                             sum(v[1] for v in read.values()), time.monotonic() - start, str(where), init_card, lr)


def progress(start: float, step: int, minutes: float | None, steps: int | None) -> float:
    """The share of the training done, by the clock or by the steps, whichever is further."""
    by_time = (time.monotonic() - start) / (minutes * 60) if minutes is not None else 0.0
    by_steps = step / steps if steps is not None else 0.0
    return min(max(by_time, by_steps), 1.0)
