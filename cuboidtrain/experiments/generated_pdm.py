"""A point distribution model drawn from the generator, for a model file that carries none.

A shipped model file holds the PDM fitted on the keypoints it was trained on
(`cuboidtrain models pack --pdm-spool`); a training checkpoint holds none. The
report's Table 3 row "T replaced with PDM" then fits one, as the paper does, on
keypoint sets drawn by the generator's `paper` scene.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from cuboidgen.config import PAPER
from cuboidgen.scene import draw_view
from cuboidtrain.models.networks import CuboidNet
from cuboidtrain.models.pdm import PointDistributionModel
from shared.shapes import get_shape


@lru_cache(maxsize=8)
def generated_pdm(shape: str, size: int, samples: int = 2000, seed: int = 0) -> PointDistributionModel:
    """Fitted on `samples` views drawn as the generator's `paper` scene draws them (cached)."""
    geometry, rng = get_shape(shape), np.random.default_rng(seed)
    sets = np.stack([draw_view(geometry, PAPER, size, rng).keypoints for _ in range(samples)])
    return PointDistributionModel.fit(sets)


def with_pdm(model: CuboidNet) -> CuboidNet:
    """`model`, given a generated PDM when its file carried none."""
    if model.pdm is None:
        model.pdm = generated_pdm(model.shape, model.size)
    return model
