"""A Point Distribution Model (Cootes et al. 1995): the linear shape space of valid octets.

Paper section 4.1: fitted on generated keypoint sets, it corrects an inaccurate
set by projecting it onto the first few principal components of shape variation
and reconstructing it from them. Shapes are compared after removing position and
scale (each set centred on its centroid and divided by its RMS radius), so the
components describe form, not where or how large a building was framed. The
projection keeps each coefficient within the range the training shapes showed
(a classic PDM clips at 3 standard deviations, but mirror flips and perspective
make these coefficients far from Gaussian, and 3 sd cut off valid shapes).

It is fitted on the keypoint sets of the spool a model was trained on and saved in
the model file (`cuboidtrain models pack`), so inference never draws a scene: a
change to the generator cannot change what a shipped model infers.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.errors import UsageError
from shared.sample import decode
from shared.spool import enumerate_spool, read_sample_bytes

MIN_SAMPLES = 1000  # the paper's initialisation size


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

    def to_dict(self) -> dict:
        """Plain lists, saved in a model file beside the weights."""
        return {name: getattr(self, name).tolist() for name in ("mean", "components", "variances", "low", "high")}

    @classmethod
    def from_dict(cls, data: dict) -> "PointDistributionModel":
        return cls(**{name: np.asarray(data[name], dtype=np.float64)
                      for name in ("mean", "components", "variances", "low", "high")})

    def active_components(self, components: int | float) -> int:
        """How many components a count or a variance fraction keeps."""
        total = len(self.variances)
        if isinstance(components, float):  # a fraction in (0, 1), as FitOptions parsed it
            explained = np.cumsum(self.variances) / self.variances.sum()
            return int(np.searchsorted(explained, components) + 1)
        if not 1 <= components <= total:
            raise UsageError(f"PDM components {components}: expected 1 to {total} for this shape class")
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


def spool_keypoints(spool: Path, shape: str, count: int = 2000) -> np.ndarray:
    """(M, N, 2) keypoint sets of up to `count` `shape` samples of a training spool, oldest first:
    the shapes the model was trained on. Corrupt or vanished samples are passed over."""
    sets = []
    for name in enumerate_spool(Path(spool)):
        data = read_sample_bytes(Path(spool), name)
        if data is None:  # evicted since the listing
            continue
        try:
            sample = decode(data)
        except ValueError:  # corrupt
            continue
        if sample.shape == shape:
            sets.append(sample.keypoints)
            if len(sets) == count:
                break
    if len(sets) < MIN_SAMPLES:
        raise UsageError(f"spool {spool}: {len(sets)} {shape} samples, a point distribution model needs "
                         f"at least {MIN_SAMPLES}")
    return np.stack(sets).astype(np.float64)
