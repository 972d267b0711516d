"""One synthetic sample from a seed: scene -> silhouette -> occlusion -> contour noise.

`make_sample(config, seed)` is a pure function of its arguments: the same seed and
config give the same sample, bit for bit, in any process on any host.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from cuboidgen.config import SceneConfig
from cuboidgen.irregular import degrade, draw_deviations, irregular, structure_points, with_structures
from cuboidgen.noise import roughen
from cuboidgen.occlusion import occlude
from shared.raster import rasterize
from cuboidgen.scene import draw_view, uniform
from shared.sample import Sample
from shared.shapes import get_shape

_MASK64 = (1 << 64) - 1
_PCG_INCREMENT = 0xDA3E39CB94B95BDB  # any odd constant: one stream, many starting states
_BITGEN = np.random.PCG64(0)
_RNG = np.random.Generator(_BITGEN)


def seeded(seed: int) -> np.random.Generator:
    """A generator in a state fixed by `seed`, reused to avoid paying for SeedSequence
    hashing (10-30 us) on every sample; splitmix64 spreads nearby seeds apart."""
    state = _splitmix64(seed) << 64 | _splitmix64(seed ^ 0x5DEECE66D)
    _BITGEN.state = {
        "bit_generator": "PCG64",
        "state": {"state": state, "inc": _PCG_INCREMENT},
        "has_uint32": 0,
        "uinteger": 0,
    }
    return _RNG


def _splitmix64(x: int) -> int:
    x = (x + 0x9E3779B97F4A7C15) & _MASK64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _MASK64
    return x ^ (x >> 31)


def sample_seed(run_seed: int, stream: int, index: int) -> int:
    """The seed of the `index`-th sample of one of a run's streams: distinct across streams. The
    daemon draws from stream 0, its samples numbered across all its workers (`daemon.Shared.next_index`),
    so `--seed S --max-samples N` means the same N samples whatever `--workers` is."""
    return _splitmix64(_splitmix64(_splitmix64(run_seed) ^ stream) ^ index)


def silhouette_box(keypoints: np.ndarray, size: int) -> tuple[int, int, int, int]:
    """The pixel-centre bounds (x0, y0, x1, y1) of the keypoints' hull, which bound the
    clean silhouette: known from the geometry, so no scan of the mask is needed."""
    xs, ys = keypoints[:, 0].tolist(), keypoints[:, 1].tolist()
    return (
        max(math.ceil(min(xs)), 0), max(math.ceil(min(ys)), 0),
        min(math.floor(max(xs)), size - 1), min(math.floor(max(ys)), size - 1),
    )


def make_sample(shape: str, scene: SceneConfig, size: int, seed: int, library) -> Sample:
    """Draw one sample. `shape` may be `mix`: the seed then picks box or twobox."""
    rng = seeded(seed)
    if shape == "mix":
        shape = "box" if rng.random() < 0.5 else "twobox"
    geometry = get_shape(shape)
    # An irregular building's roof, chimney, parapet or neighbour join the silhouette, framed with it, that
    # the occluders cut; the clean mask, the Refiner's target, stays the box's (cuboidgen.irregular).
    deviations = draw_deviations(geometry, scene, rng) if irregular(scene) else None
    view = draw_view(geometry, scene, size, rng,
                     beside=(lambda camera: structure_points(deviations, geometry, camera)) if deviations else None)
    clean = rasterize(geometry, view.keypoints, size)
    built = with_structures(clean, deviations, geometry, view) if deviations else clean
    occluded, occluders = occlude(built, library, scene, rng,
                                  box=silhouette_box(view.keypoints, size) if built is clean else None)
    amount = uniform(rng, scene.contour_noise) * size / 256
    wavelength = uniform(rng, scene.noise_wavelength) * size / 256
    noisy = roughen(occluded, amount, wavelength, rng)
    if deviations:
        noisy = degrade(noisy, deviations, rng)
    visible = cv2.countNonZero(occluded.view(np.uint8))  # occlusion only removes pixels
    params = {
        "scene": scene.name,
        **view.params,
        "occluders": occluders,
        "occluded_fraction": 1.0 - visible / max(cv2.countNonZero(built.view(np.uint8)), 1),
        "contour_noise": amount,
        "noise_wavelength": wavelength,
    }
    if deviations is not None:
        params["deviations"] = deviations
    return Sample(
        shape=shape, size=size, seed=seed, keypoints=view.keypoints, ratios=view.ratios,
        noisy=noisy, clean=clean, params=params,
    )

