"""The shape classifier: a fourth, small network that calls a rough silhouette box or twobox.

The Refiner, Estimator and Tabulator of each class fit their own shape; which class a building is
was decided by the fitted cuboids' silhouettes alone (the richer class when it explains more by a
margin). On a clean mask that decides (a twobox's step is in its outline), but on a rough one the
step drowns in what real outlines add (a roof line, a chimney, a neighbour's corner, blobby edges):
evidence read off the two fitted cuboids called irregular one-box buildings box on 77% and
twoboxes twobox on 84%, and no rule on it did better on both (BENCHMARKS.md, "Shape selection").
This network reads the framed mask itself (64 px, grey, as the shipped models read it) and gives
the probability that it is a twobox; `cuboidtrain.fit.shape_call` decides when it is asked.

Four strided blocks and a linear layer, 0.2 M weights. A mirrored building is the same class, so
the probability is the mean of the logits of the mask and its mirror: a call never depends on which
way the building faces (it was trained on both). The file is weights (float16), a format, a version
and a card saying how it was trained; it loads through the checkpoints' CRC check, so a flipped bit
is refused, not used.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from cuboidtrain.models.checkpoint import non_finite_weights, read_torch_file
from shared.errors import UsageError
from shared.files import atomic_path

CLASSIFIER_FORMAT = "cuboid-fit/shape-classifier"
CLASSIFIER_VERSION = 1
CLASSIFIER_SIZE = 64  # px, the framed input's side (the shipped models')
CLASSES = ("box", "twobox")  # the logit is twobox's


def block(into: int, out: int) -> nn.Sequential:
    """A 3x3 convolution, then a strided one: the side halves, the channels grow."""
    return nn.Sequential(nn.Conv2d(into, out, 3, padding=1), nn.BatchNorm2d(out), nn.ReLU(),
                         nn.Conv2d(out, out, 3, padding=1, stride=2), nn.BatchNorm2d(out), nn.ReLU())


class ShapeClassifier(nn.Sequential):
    """(B, 1, 64, 64) framed grey masks in [0, 1] -> (B,) twobox logits."""

    def __init__(self):
        super().__init__(block(1, 16), block(16, 32), block(32, 64), block(64, 96), nn.AdaptiveAvgPool2d(1),
                         nn.Flatten(), nn.Linear(96, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x)[:, 0]

    def folded(self) -> "ShapeClassifier":
        """For inference only: each BatchNorm folded into the convolution before it (the same function in
        eval mode, a quarter faster on one thread: 1.84 -> 1.59 ms for the mask and its mirror)."""
        for stage in list(self)[:4]:  # the four blocks
            for conv, norm in ((0, 1), (3, 4)):
                stage[conv] = fuse_conv_bn_eval(stage[conv], stage[norm])
                stage[norm] = nn.Identity()
        return self

    @torch.inference_mode()
    def twobox_probability(self, framed: np.ndarray) -> float:
        """P(twobox) of one framed (64, 64) mask: the mean logit of it and its mirror, through a sigmoid."""
        if framed.shape != (CLASSIFIER_SIZE, CLASSIFIER_SIZE):
            raise ValueError(f"framed mask {framed.shape}: expected ({CLASSIFIER_SIZE}, {CLASSIFIER_SIZE})")
        x = torch.from_numpy(np.ascontiguousarray(framed, dtype=np.float32))[None, None]
        logits = self(torch.cat([x, x.flip(-1)]))
        return float(torch.sigmoid(logits.mean()))


def save_classifier(path: Path, net: ShapeClassifier, card: dict) -> None:
    """The weights (float16: half the bytes, the same calls; BENCHMARKS.md) and the card, atomically."""
    weights = {k: v.half() if v.is_floating_point() else v for k, v in net.state_dict().items()}
    payload = {"format": CLASSIFIER_FORMAT, "version": CLASSIFIER_VERSION, "model": weights, "card": card}
    with atomic_path(Path(path)) as tmp:
        torch.save(payload, tmp)


def load_classifier(path: Path, folded: bool = True) -> tuple[ShapeClassifier, dict]:
    """The classifier (float32, eval mode, its BatchNorms folded for inference unless `folded` is False:
    a start to train on) and its card; a one-line UsageError for a missing, damaged or foreign file
    (`check_intact`: a flipped bit is refused, not used)."""
    return checked_classifier(Path(path), read_torch_file(Path(path), "shape classifier", weights_only=True), folded)


def checked_classifier(path: Path, payload: object, folded: bool = True) -> tuple[ShapeClassifier, dict]:
    """The classifier and card of `payload`, what `path` holds (`read_torch_file`), checked as
    `load_classifier` checks it."""
    if not isinstance(payload, dict) or payload.get("format") != CLASSIFIER_FORMAT:
        raise UsageError(f"shape classifier {path}: not a shape classifier (expected format {CLASSIFIER_FORMAT!r})")
    if payload.get("version") != CLASSIFIER_VERSION:
        raise UsageError(f"shape classifier {path}: format version {payload.get('version')!r}, "
                         f"expected {CLASSIFIER_VERSION}")
    bad, total = non_finite_weights(payload["model"])
    if bad:
        raise UsageError(f"shape classifier {path}: {bad} of {total} weights are NaN or Infinity: not a model to use")
    net = ShapeClassifier()
    net.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in payload["model"].items()})
    net.eval()
    return (net.folded() if folded else net), payload["card"]
