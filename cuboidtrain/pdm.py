"""A Point Distribution Model (Cootes et al. 1995): the linear shape space of valid octets.

Paper section 4.1: fitted on generated keypoint sets, it corrects an inaccurate
set by projecting it onto the first few principal components of shape variation
and reconstructing it from them. Shapes are compared after removing position and
scale (each set centred on its centroid and divided by its RMS radius), so the
components describe form, not where or how large a building was framed. The
projection keeps each coefficient within the range the training shapes showed
(a classic PDM clips at 3 standard deviations, but mirror flips and perspective
make these coefficients far from Gaussian, and 3 sd cut off valid shapes).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

MIN_SAMPLES = 1000  # the paper's initialisation size


def parse_components(value: str | int | float) -> int | float:
    """`--pdm-components`: an integer count (>= 1) or a variance fraction in (0, 1)."""
    text = str(value).strip()
    try:
        number = float(text)
    except ValueError:
        number = float("nan")
    if number >= 1 and number == int(number) and "." not in text:
        return int(number)
    if 0 < number < 1:
        return number
    raise ValueError(f"PDM components {value!r}: expected a count of components (1, 2, ...) "
                     f"or a fraction of the shape variance to keep, between 0 and 1")


def normalise(keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M, N, 2) -> unit-RMS centred shapes (M, N, 2), centroids (M, 1, 2), scales (M, 1, 1)."""
    centroid = keypoints.mean(axis=1, keepdims=True)
    centred = keypoints - centroid
    scale = np.sqrt((centred**2).sum(axis=(1, 2), keepdims=True) / keypoints.shape[1])
    scale = np.maximum(scale, 1e-9)  # all points on one spot: nothing to scale
    return centred / scale, centroid, scale


@dataclass(frozen=True)
class PointDistributionModel:
    mean: np.ndarray  # (2N,) mean normalised shape, (x0, y0, x1, y1, ...)
    components: np.ndarray  # (K, 2N) principal directions, by decreasing variance
    variances: np.ndarray  # (K,) variance along each
    low: np.ndarray  # (K,) smallest coefficient among the training shapes, less a 10% margin
    high: np.ndarray  # (K,) largest, plus the margin

    @classmethod
    def fit(cls, keypoint_sets: np.ndarray) -> "PointDistributionModel":
        """PCA of (M, N, 2) keypoint sets, M >= 1,000."""
        sets = np.asarray(keypoint_sets, dtype=np.float64)
        if sets.ndim != 3 or sets.shape[2] != 2:
            raise ValueError(f"keypoint sets of shape {sets.shape}: expected (M, N, 2)")
        if len(sets) < MIN_SAMPLES:
            raise ValueError(f"{len(sets)} keypoint sets: a PDM needs at least {MIN_SAMPLES}")
        shapes = normalise(sets)[0].reshape(len(sets), -1)
        mean = shapes.mean(axis=0)
        _, singular, vt = np.linalg.svd(shapes - mean, full_matrices=False)
        coefficients = (shapes - mean) @ vt.T
        low, high = coefficients.min(axis=0), coefficients.max(axis=0)
        margin = 0.1 * (high - low)
        return cls(mean=mean, components=vt, variances=singular**2 / (len(sets) - 1),
                   low=low - margin, high=high + margin)

    @classmethod
    def from_generator(cls, shape: str, size: int, samples: int = 2000, seed: int = 0) -> "PointDistributionModel":
        """Fitted on `samples` views drawn as the generator's `paper` scene draws them (cached)."""
        return _fitted(shape, size, samples, seed)

    def active_components(self, components: int | float) -> int:
        """How many components a count or a variance fraction keeps."""
        total = len(self.variances)
        if isinstance(components, float):
            if not 0 < components < 1:
                raise ValueError(f"PDM variance fraction {components}: expected a number in (0, 1)")
            explained = np.cumsum(self.variances) / self.variances.sum()
            return int(np.searchsorted(explained, components) + 1)
        if not 1 <= components <= total:
            raise ValueError(f"PDM components {components}: expected 1 to {total} for this shape class")
        return int(components)

    def project(self, keypoints: np.ndarray, components: int | float) -> np.ndarray:
        """(B, N, 2) px -> the nearest shapes in the model's span, (B, N, 2) px, same place and scale."""
        k = self.active_components(components)
        points = np.asarray(keypoints, dtype=np.float64)
        shapes, centroid, scale = normalise(points)
        basis = self.components[:k]  # (k, 2N)
        coefficients = (shapes.reshape(len(points), -1) - self.mean) @ basis.T  # (B, k)
        coefficients = np.clip(coefficients, self.low[:k], self.high[:k])
        rebuilt = (self.mean + coefficients @ basis).reshape(points.shape)
        # Reconstruction can shift the centroid and RMS radius slightly; undo exactly what normalise did.
        rebuilt = normalise(rebuilt)[0]
        return rebuilt * scale + centroid


@lru_cache(maxsize=8)
def _fitted(shape: str, size: int, samples: int, seed: int) -> PointDistributionModel:
    from cuboidgen.config import PAPER
    from cuboidgen.scene import draw_view
    from shared.shapes import get_shape

    geometry, rng = get_shape(shape), np.random.default_rng(seed)
    sets = np.stack([draw_view(geometry, PAPER, size, rng).keypoints for _ in range(samples)])
    return PointDistributionModel.fit(sets)
