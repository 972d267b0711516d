"""The localization experiment (paper section 5.1, eq. 2, Figures 10-12).

Draw a street of N random buildings, a noisy, occluded silhouette of each from
the generator, predict every building's ratios through the Fitter (or an oracle:
the true ratios with relative noise), and score every predicted sub-sequence of
length m against every true one. The street and the matching are
`cuboidtrain.localize`'s.

Positions are 0-based here and 1-based in what people read (tables, figures).
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, replace

import numpy as np

from cuboidgen.config import SceneConfig, load_scene
from cuboidgen.occluders import OccluderLibrary
from cuboidgen.scene import uniform
from cuboidgen.synth import make_sample, sample_seed
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.localize import (EXTENTS, Building, accuracy, box_model, start_probabilities, street_ratios)
from cuboidtrain.models.networks import CuboidNet
from cuboidtrain.fit.options import FitOptions
from shared.errors import UsageError
from shared.sample import Sample
from shared.shapes import RATIO_KEYS

log = logging.getLogger(__name__)


def draw_street(count: int, scene: SceneConfig, rng: np.random.Generator) -> list[Building]:
    """`count` buildings with extents drawn uniformly from the scene's ranges (Table 4's scales)."""
    return [Building(f"#{k + 1}", *(uniform(rng, getattr(scene, e)) for e in EXTENTS)) for k in range(count)]


def silhouette_of(building: Building, scene: SceneConfig, size: int, seed: int, library) -> Sample:
    """A new random view of this very building: the generator's own sample (pose, framing,
    occlusion, contour noise from `seed`), its extent ranges pinned to the building's."""
    pinned = replace(scene, **{e: (getattr(building, e),) * 2 for e in EXTENTS})
    return make_sample("box", pinned, size, seed, library)


def predict_ratios(masks: list[np.ndarray], fitter: Fitter) -> np.ndarray:
    """(N, 2) ratios predicted for bool masks as `infer` would: the building (its pieces), framed
    for the model, R (iterated), S, T (T's ratios whatever reads the keypoints)."""
    predicted = []
    for k, mask in enumerate(masks):
        if not mask.any():
            raise UsageError(f"building {k + 1}: its silhouette is empty (occluded away)")
        ratios = fitter.fit(mask).ratios
        predicted.append([ratios[key] for key in RATIO_KEYS])
    return np.array(predicted).reshape(len(masks), len(RATIO_KEYS))


def oracle_ratios(true: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """The true ratios times (1 + noise * N(0, 1)), each independently: checks the matching."""
    return true * (1.0 + noise * rng.standard_normal(true.shape))


@dataclass(frozen=True)
class ExperimentConfig:
    """Everything `cuboidtrain localize` (without --street) does; options map onto fields."""

    buildings: int = 100  # N, buildings per street
    max_m: int = 30  # M, the longest sub-sequence
    top_l: int = 5  # L, the widest top-l
    seed: int = 0
    streets: int = 1  # independent streets; acc is their mean
    scene: str = "paper"  # the generator's scene: extent ranges, views, occlusion, noise
    mask_size: int | None = None  # px of the drawn masks; None: the model's size
    oracle: bool = False  # true ratios with relative noise instead of the networks
    oracle_noise: float = 0.0  # the oracle's relative std
    example_m: int = 4  # Figure 12: sub-sequence length of the example
    example_start: int | None = None  # its true start, 1-based; None: the middle of the street
    temperature: float = 1.0  # softmax(-distance / temperature)

    def validate(self) -> "ExperimentConfig":
        if self.buildings < 1:
            raise UsageError(f"--buildings {self.buildings}: expected 1 or more")
        if not 1 <= self.max_m <= self.buildings:
            raise UsageError(f"--max-m {self.max_m}: expected 1 to --buildings ({self.buildings})")
        if self.top_l < 1:
            raise UsageError(f"--top-l {self.top_l}: expected 1 or more")
        if self.streets < 1:
            raise UsageError(f"--streets {self.streets}: expected 1 or more")
        if not self.oracle_noise >= 0:
            raise UsageError(f"--oracle-noise {self.oracle_noise}: expected 0 or more (a relative std)")
        if self.mask_size is not None and not 16 <= self.mask_size <= 4096:
            raise UsageError(f"--mask-size {self.mask_size}: expected 16 to 4096 px")
        if not 1 <= self.example_m <= self.buildings:
            raise UsageError(f"--example-m {self.example_m}: expected 1 to --buildings ({self.buildings})")
        last = self.buildings - self.example_m + 1
        if self.example_start is not None and not 1 <= self.example_start <= last:
            raise UsageError(f"--example-start {self.example_start}: expected 1 to {last} "
                             f"(a sub-sequence of {self.example_m} in {self.buildings} buildings)")
        if not self.temperature > 0:
            raise UsageError(f"--temperature {self.temperature}: expected a positive number")
        load_scene(self.scene)
        return self


def street_predictions(config: ExperimentConfig, street_index: int, fitter: Fitter | None,
                       library) -> tuple[list[Building], np.ndarray]:
    """One street of the experiment and its predicted ratios (model or oracle)."""
    rng = np.random.default_rng([config.seed, street_index])
    scene = load_scene(config.scene)
    street = draw_street(config.buildings, scene, rng)
    true = street_ratios(street)
    if config.oracle:
        return street, oracle_ratios(true, config.oracle_noise, rng)
    size = config.mask_size or fitter.models[0].size
    masks = [silhouette_of(b, scene, size, sample_seed(config.seed, street_index, k), library).noisy
             for k, b in enumerate(street)]
    return street, predict_ratios(masks, fitter)


def ratio_errors(true: np.ndarray, predicted: np.ndarray) -> dict:
    """Mean absolute and relative error per ratio, over every building of every street."""
    absolute, relative = np.abs(predicted - true), np.abs(predicted - true) / true
    return {key: {"mean_abs": float(absolute[:, i].mean()), "mean_rel": float(relative[:, i].mean())}
            for i, key in enumerate(RATIO_KEYS)}


def example(config: ExperimentConfig, street: list[Building], predicted: np.ndarray) -> dict:
    """Figure 12 on the first street: one predicted sub-sequence against every start."""
    m = config.example_m
    start = (config.example_start or (config.buildings - m) // 2 + 1) - 1
    distances, probabilities = start_probabilities(street_ratios(street), predicted[start : start + m],
                                                   config.temperature)
    return {"m": m, "true_start": start, "distances": distances.tolist(), "probabilities": probabilities.tolist()}


def first_m_reaching(acc: np.ndarray, level: float = 0.5) -> list[int | None]:
    """Per l, the shortest m with acc(m, l) >= level (None if no m up to M does)."""
    return [next((m + 1 for m in range(acc.shape[0]) if acc[m, l] >= level), None) for l in range(acc.shape[1])]


def run_experiment(config: ExperimentConfig, models: list[CuboidNet] | None = None,
                   checkpoints: list[str] | None = None, options: FitOptions | None = None) -> dict:
    """Eq. (2) over `config.streets` streets: the mean acc(m, l) and what made it; the box
    model fits each mask with `options`, as `infer --shape box` would."""
    config.validate()
    options = replace(options or FitOptions(), shape="box").validate()
    model = None if config.oracle else box_model(models or [])
    fitter = None if model is None else Fitter([model], options)
    library = None if config.oracle else OccluderLibrary.builtin()
    per_street, trues, preds, streets, first = [], [], [], [], None
    for s in range(config.streets):
        street, predicted = street_predictions(config, s, fitter, library)
        first = first or (street, predicted)
        true = street_ratios(street)
        per_street.append(accuracy(true, predicted, config.max_m, config.top_l))
        trues.append(true), preds.append(predicted)
        streets.append({"true": true.tolist(), "predicted": predicted.tolist()})
        log.info("street %d of %d: acc(1, 1) %.2f", s + 1, config.streets, per_street[-1][0, 0])
    acc = np.mean(per_street, axis=0)
    return {
        "format": "cuboid-fit/localization-experiment", "version": 1,
        "settings": asdict(config) | {"refine_steps": options.refine_steps, "margin": options.margin,
                                       "cuboid": options.cuboid,
                                       "checkpoints": list(checkpoints or []),
                                       "model": None if model is None else {"shape": model.shape, "size": model.size}},
        "m": list(range(1, config.max_m + 1)), "l": list(range(1, config.top_l + 1)),
        "acc": acc.tolist(),
        "acc_per_street": [a.tolist() for a in per_street],
        "first_m_at_half": first_m_reaching(acc),
        "ratio_error": ratio_errors(np.concatenate(trues), np.concatenate(preds)),
        "example": example(config, *first),
        "streets": streets,
    }



