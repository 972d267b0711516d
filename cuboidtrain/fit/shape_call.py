"""Who calls the shape class of a mask: its silhouette, or the shape classifier.

A clean silhouette decides (its twobox's step is in the outline: the fitted cuboids' IoU chooses,
`cuboid.choose_cuboid`, 99.3-100% right on generated twoboxes). A rough one does not: on noisy
masks the shape classifier (`cuboidtrain.models.classifier`) reads the framed mask, and where it is
SURE its call stands among the plausible fits, where the IoU would have chosen by a margin it cannot
read; where it is not, the silhouettes decide as on a clean mask.
"Clean" is `mask_fit.polygonal`: one outline of a few straight sides, as the restarts read it.

The record says which decided and, for the classifier, its probability (`ShapeCall.record`).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from cuboidtrain.fit.masks import frame
from cuboidtrain.geometry.mask_fit import polygonal
from cuboidtrain.models.classifier import CLASSIFIER_SIZE, ShapeClassifier, load_classifier
from cuboidtrain.models.device import one_thread

log = logging.getLogger(__name__)

SILHOUETTE: Literal["silhouette"] = "silhouette"
CLASSIFIER: Literal["classifier"] = "classifier"
# The classifier's call stands where it gives its class at least this probability; under it the
# silhouettes decide. On the tuning seeds' rough masks (150 a scene and class) 0.8 was better than or
# equal to the silhouettes alone on every scene and class, where 0.5 lost 2-4 points on twoboxes
# (BENCHMARKS.md, "Shape selection").
SURE = 0.8


@dataclass(frozen=True)
class ShapeCall:
    by: Literal["silhouette", "classifier"]  # SILHOUETTE: the fitted cuboids' IoU chose; CLASSIFIER: its sure call
    twobox_probability: float | None = None  # the classifier's, where it was asked

    @property
    def shape(self) -> str | None:
        """The class the classifier calls; None where the silhouette decides."""
        if self.by != CLASSIFIER:
            return None
        return "twobox" if self.twobox_probability > 0.5 else "box"

    def record(self) -> dict:
        p = self.twobox_probability
        return {"by": self.by, "twobox_probability": None if p is None else round(p, 4)}


def classifier_input(mask: np.ndarray) -> np.ndarray:
    """(64, 64) float32: the mask's object framed as the shipped models read it (grey, the default margin)."""
    return frame(mask, CLASSIFIER_SIZE, grey=True)[0].astype(np.float32)


def call_shape(classifier: ShapeClassifier | None, mask: np.ndarray) -> ShapeCall | None:
    """None without a classifier; the silhouette's call on a clean mask, or where the classifier is
    not SURE of its class (its probability kept); else the classifier's."""
    if classifier is None:
        return None
    if polygonal(mask):
        return ShapeCall(SILHOUETTE)
    with one_thread(torch.device("cpu")):  # the same probability on every machine (`device.one_thread`)
        p = classifier.twobox_probability(classifier_input(mask))
    return ShapeCall(CLASSIFIER if max(p, 1.0 - p) >= SURE else SILHOUETTE, p)


@lru_cache(maxsize=4)
def cached_classifier(path: Path) -> ShapeClassifier:
    """One load per file and process (a pool's workers each load it once)."""
    return load_classifier(path)[0]


def shipped_classifier() -> ShapeClassifier | None:
    """The shipped classifier (`zoo.classifier_path`), or None with a warning once where the model
    folder has none (a $CUBOID_MODELS folder of box and twobox models only): the silhouette decides."""
    from cuboidtrain.models.zoo import classifier_path

    path = classifier_path()
    if not path.is_file():
        warn_missing(path)
        return None
    return cached_classifier(path)


@lru_cache(maxsize=None)
def warn_missing(path: Path) -> None:
    log.warning("no shape classifier at %s: the fitted cuboids' silhouettes alone choose the class", path)
