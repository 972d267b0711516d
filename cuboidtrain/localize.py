"""Localization from sequences of building ratios (paper section 5).

A street is known building by building (width, height, depth). Photos of m
consecutive buildings give predicted ratios (depth/height, width/height) per
building; the sub-sequence of the street whose true ratios are nearest in L2
distance is where the photos were taken.

Two uses:

* the experiment (eq. 2): draw a street of N random buildings, a noisy, occluded
  silhouette of each from the generator, predict every building's ratios with the
  full inference chain (or an oracle: the true ratios with relative noise), and
  score every predicted sub-sequence of length m against every true one;
* the practical command: a street's JSON and the user's masks, in street order,
  give the ranked start positions with probabilities (softmax of negative
  distances, Figure 12).

Positions are 0-based here and 1-based in what people read (tables, figures).
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from cuboidgen.config import SceneConfig, load_scene
from cuboidgen.occluders import OccluderLibrary
from cuboidgen.scene import uniform
from cuboidgen.synth import make_sample, sample_seed
from cuboidtrain.device import resolve_device
from cuboidtrain.infer import fit, infer_paths
from cuboidtrain.masks import components, frame
from cuboidtrain.networks import CuboidNet
from shared.sample import Sample
from shared.shapes import RATIO_KEYS

log = logging.getLogger(__name__)

STREET_FORMAT = "cuboid-fit/street"
STREET_VERSION = 1
EXTENTS = ("width", "height", "depth")


# --- the street ------------------------------------------------------------------

@dataclass(frozen=True)
class Building:
    """One building of a street: its extents in any one unit (only ratios are used)."""

    name: str
    width: float
    height: float
    depth: float

    @property
    def ratios(self) -> np.ndarray:
        """(2,) in RATIO_KEYS order: depth/height, width/height."""
        return np.array([self.depth / self.height, self.width / self.height])


def street_ratios(street: list[Building]) -> np.ndarray:
    """(N, 2) true ratios of the street's buildings, in street order."""
    return np.array([b.ratios for b in street]).reshape(len(street), len(RATIO_KEYS))


def read_street(path: str | Path) -> list[Building]:
    """A street JSON file (README: "Localization"); ValueError names what is wrong."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"--street {path}: cannot read it ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise ValueError(f"--street {path}: not JSON ({exc})") from None
    return street_from_dict(data, source=str(path))


def street_from_dict(data, source: str = "street") -> list[Building]:
    if not isinstance(data, dict):
        raise ValueError(f"{source}: a JSON {type(data).__name__}, expected an object with format, version and buildings")
    if data.get("format") != STREET_FORMAT:
        raise ValueError(f"{source}: format {data.get('format')!r}, expected {STREET_FORMAT!r}")
    if data.get("version") != STREET_VERSION:
        raise ValueError(f"{source}: version {data.get('version')!r}, expected {STREET_VERSION}")
    buildings = data.get("buildings")
    if not isinstance(buildings, list) or not buildings:
        raise ValueError(f"{source}: buildings = {buildings!r}, expected a non-empty list of "
                         f"{{\"name\", \"width\", \"height\", \"depth\"}} objects")
    return [building_from_dict(b, f"{source}: buildings[{k}]", default_name=f"#{k + 1}")
            for k, b in enumerate(buildings)]


def building_from_dict(data, where: str, default_name: str) -> Building:
    if not isinstance(data, dict):
        raise ValueError(f"{where} = {data!r}, expected an object with width, height and depth")
    extents = {}
    for key in EXTENTS:
        if key not in data:
            raise ValueError(f"{where}: missing key {key!r} (expected width, height and depth, in any one unit)")
        value = data[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{where}.{key} = {value!r}, expected a positive number")
        extents[key] = float(value)
    name = data.get("name", default_name)
    if not isinstance(name, str):
        raise ValueError(f"{where}.name = {name!r}, expected a string")
    return Building(name=name, **extents)


def street_to_dict(street: list[Building]) -> dict:
    return {"format": STREET_FORMAT, "version": STREET_VERSION, "buildings": [asdict(b) for b in street]}


def draw_street(count: int, scene: SceneConfig, rng: np.random.Generator) -> list[Building]:
    """`count` buildings with extents drawn uniformly from the scene's ranges (Table 4's scales)."""
    return [Building(f"#{k + 1}", *(uniform(rng, getattr(scene, e)) for e in EXTENTS)) for k in range(count)]


def silhouette_of(building: Building, scene: SceneConfig, size: int, seed: int, library) -> Sample:
    """A new random view of this very building: the generator's own sample (pose, framing,
    occlusion, contour noise from `seed`), its extent ranges pinned to the building's."""
    pinned = replace(scene, **{e: (getattr(building, e),) * 2 for e in EXTENTS})
    return make_sample("box", pinned, size, seed, library)


# --- matching: eq. (2) and Figure 12 -------------------------------------------------

def _check_ratios(true: np.ndarray, predicted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    true, predicted = np.asarray(true, np.float64), np.asarray(predicted, np.float64)
    if true.ndim != 2 or true.shape != predicted.shape:
        raise ValueError(f"ratios: true {true.shape} and predicted {predicted.shape}, expected the same (N, R) shape")
    if not (np.isfinite(true).all() and np.isfinite(predicted).all()):
        raise ValueError("ratios: expected finite values (a NaN or inf ratio cannot be matched)")
    return true, predicted


def subsequence_distances(true: np.ndarray, predicted: np.ndarray, max_m: int):
    """Yield (m, D2) for m = 1..max_m, D2 (N-m+1, N-m+1) the squared L2 distance between the
    predicted sub-sequence starting at i and the true one starting at j (ratio vectors of
    the m buildings, concatenated). D2_m = D2_{m-1} + the m-th buildings' term, so all
    lengths cost O(max_m N^2)."""
    true, predicted = _check_ratios(true, predicted)
    per_building = ((predicted[:, None, :] - true[None, :, :]) ** 2).sum(axis=-1)  # (N, N)
    n = len(true)
    squared = np.zeros((n, n))
    for m in range(1, max_m + 1):
        squared = squared[: n - m + 1, : n - m + 1] + per_building[m - 1 :, m - 1 :]
        yield m, squared


def true_ranks(distances: np.ndarray) -> np.ndarray:
    """(K, K) distances (row i: predicted sub-sequence i against every true start j) -> (K,)
    the rank of the true start i, 1 = nearest. A tie counts against the true start: its
    rank is 1 + the number of other starts at a distance <= its own."""
    own = np.diagonal(distances)[:, None]
    return (distances <= own).sum(axis=1)  # the true start itself counts as the 1


def accuracy(true: np.ndarray, predicted: np.ndarray, max_m: int, top_l: int) -> np.ndarray:
    """Eq. (2): (max_m, top_l) array, [m-1, l-1] = acc(m, l), the fraction of the N-m+1
    predicted sub-sequences of length m whose true start is among the l nearest of the
    N-m+1 true sub-sequences (candidates: every start 0..N-m)."""
    n = len(np.asarray(true))
    if not 1 <= max_m <= n:
        raise ValueError(f"--max-m {max_m}: expected 1 to the number of buildings ({n})")
    if top_l < 1:
        raise ValueError(f"--top-l {top_l}: expected 1 or more")
    acc = np.empty((max_m, top_l))
    for m, squared in subsequence_distances(true, predicted, max_m):
        ranks = true_ranks(squared)  # squared distances order (and tie) as the distances do
        acc[m - 1] = [(ranks <= l).mean() for l in range(1, top_l + 1)]
    return acc


def start_probabilities(true: np.ndarray, predicted: np.ndarray, temperature: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Figure 12: predicted ratios of m consecutive buildings (m, R) against every start
    0..N-m of the street's true ratios (N, R) -> (distances, softmax(-distance / T))."""
    true, predicted = np.asarray(true, np.float64), np.asarray(predicted, np.float64)
    m = len(predicted)
    if not 1 <= m <= len(true):
        raise ValueError(f"{m} predicted buildings for a street of {len(true)}: expected 1 to {len(true)}")
    if not temperature > 0:
        raise ValueError(f"--temperature {temperature}: expected a positive number")
    windows = np.lib.stride_tricks.sliding_window_view(true, m, axis=0)  # (N-m+1, R, m)
    distances = np.sqrt(((windows - predicted.T[None]) ** 2).sum(axis=(1, 2)))
    logits = -distances / temperature
    weights = np.exp(logits - logits.max())  # shifted: no overflow, same softmax
    return distances, weights / weights.sum()


def rank_starts(street: list[Building], predicted: np.ndarray, temperature: float = 1.0) -> list[dict]:
    """Every start position of the photographed sequence, most probable first (ties: the
    earlier start), with the buildings it covers, its distance and probability."""
    predicted = np.asarray(predicted, np.float64).reshape(-1, len(RATIO_KEYS))
    distances, probabilities = start_probabilities(street_ratios(street), predicted, temperature)
    order = np.argsort(-probabilities, kind="stable")
    m = len(predicted)
    return [{"rank": r + 1, "start": int(j), "buildings": [b.name for b in street[j : j + m]],
             "distance": float(distances[j]), "probability": float(probabilities[j])}
            for r, j in enumerate(order)]


# --- predicted ratios ------------------------------------------------------------------

def box_model(models: list[CuboidNet]) -> CuboidNet:
    """The box model among those given: a street's buildings are single boxes."""
    for model in models:
        if model.shape == "box":
            return model
    raise ValueError(f"--checkpoint: localization needs a box model (a street's buildings are single boxes); "
                     f"got {', '.join(m.shape for m in models) or 'none'}")


def predict_ratios(masks: list[np.ndarray], model: CuboidNet, refine_steps: int | None, margin: float,
                   device: str | torch.device = "cpu") -> np.ndarray:
    """(N, 2) ratios predicted for bool masks as `infer` would: the largest component,
    framed for the model, R (iterated), S, T (T's ratios whatever reads the keypoints)."""
    device = resolve_device(device)
    model.to(device).eval()
    predicted = []
    for k, mask in enumerate(masks):
        parts = components(mask)
        if not parts or not parts[0].any():
            raise ValueError(f"building {k + 1}: its silhouette is empty (occluded away)")
        framed, _ = frame(parts[0], model.size, margin)  # as infer frames a component
        fitted = fit(model, framed, refine_steps=refine_steps, device=device)
        predicted.append([fitted["ratios"][key] for key in RATIO_KEYS])
    return np.array(predicted).reshape(len(masks), len(RATIO_KEYS))


def oracle_ratios(true: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """The true ratios times (1 + noise * N(0, 1)), each independently: checks the matching."""
    return true * (1.0 + noise * rng.standard_normal(true.shape))


def localize_masks(street: list[Building], masks: list[str], models: list[CuboidNet], refine_steps: int | None = 1,
                   margin: float = 0.1, device: str | torch.device = "cpu", temperature: float = 1.0) -> dict:
    """The practical command: the user's masks of consecutive buildings (street order) ->
    their predicted ratios and every start position ranked by probability."""
    if len(masks) > len(street):
        raise ValueError(f"{len(masks)} masks for a street of {len(street)} buildings: "
                         f"expected at most as many masks as buildings")
    if not temperature > 0:
        raise ValueError(f"--temperature {temperature}: expected a positive number")
    records = infer_paths(masks, [box_model(models)], shape="box", refine_steps=refine_steps,
                          margin=margin, device=device)
    for record in records:
        if record["error"] is not None:
            raise ValueError(f"{record['error']} (every mask is needed: the sequence cannot have a gap)")
    predicted = np.array([[r["ratios"][k] for k in RATIO_KEYS] for r in records])
    return {
        "format": "cuboid-fit/localization", "version": 1, "temperature": temperature,
        "masks": [{"input": r["input"], "ratios": r["ratios"], "confidence": r["confidence"]} for r in records],
        "street": street_to_dict(street),
        "ranking": rank_starts(street, predicted, temperature),
    }


# --- the experiment (section 5.1) -------------------------------------------------------

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
    refine_steps: int | None = 1  # Refiner passes (None: until it settles), as `infer`
    margin: float = 0.1  # framing margin, as `infer`
    oracle: bool = False  # true ratios with relative noise instead of the networks
    oracle_noise: float = 0.0  # the oracle's relative std
    example_m: int = 4  # Figure 12: sub-sequence length of the example
    example_start: int | None = None  # its true start, 1-based; None: the middle of the street
    temperature: float = 1.0  # softmax(-distance / temperature)

    def validate(self) -> "ExperimentConfig":
        if self.buildings < 1:
            raise ValueError(f"--buildings {self.buildings}: expected 1 or more")
        if not 1 <= self.max_m <= self.buildings:
            raise ValueError(f"--max-m {self.max_m}: expected 1 to --buildings ({self.buildings})")
        if self.top_l < 1:
            raise ValueError(f"--top-l {self.top_l}: expected 1 or more")
        if self.streets < 1:
            raise ValueError(f"--streets {self.streets}: expected 1 or more")
        if not self.oracle_noise >= 0:
            raise ValueError(f"--oracle-noise {self.oracle_noise}: expected 0 or more (a relative std)")
        if self.mask_size is not None and not 16 <= self.mask_size <= 4096:
            raise ValueError(f"--mask-size {self.mask_size}: expected 16 to 4096 px")
        if not 1 <= self.example_m <= self.buildings:
            raise ValueError(f"--example-m {self.example_m}: expected 1 to --buildings ({self.buildings})")
        last = self.buildings - self.example_m + 1
        if self.example_start is not None and not 1 <= self.example_start <= last:
            raise ValueError(f"--example-start {self.example_start}: expected 1 to {last} "
                             f"(a sub-sequence of {self.example_m} in {self.buildings} buildings)")
        if not self.temperature > 0:
            raise ValueError(f"--temperature {self.temperature}: expected a positive number")
        load_scene(self.scene)
        return self


def street_predictions(config: ExperimentConfig, street_index: int, model: CuboidNet | None,
                       library, device) -> tuple[list[Building], np.ndarray]:
    """One street of the experiment and its predicted ratios (model or oracle)."""
    rng = np.random.default_rng([config.seed, street_index])
    scene = load_scene(config.scene)
    street = draw_street(config.buildings, scene, rng)
    true = street_ratios(street)
    if config.oracle:
        return street, oracle_ratios(true, config.oracle_noise, rng)
    size = config.mask_size or model.size
    masks = [silhouette_of(b, scene, size, sample_seed(config.seed, street_index, k), library).noisy
             for k, b in enumerate(street)]
    return street, predict_ratios(masks, model, config.refine_steps, config.margin, device)


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
                   checkpoints: list[str] | None = None, device: str | torch.device = "cpu") -> dict:
    """Eq. (2) over `config.streets` streets: the mean acc(m, l) and what made it."""
    config.validate()
    model = None if config.oracle else box_model(models or [])
    library = None if config.oracle else OccluderLibrary.builtin()
    per_street, trues, preds, streets, first = [], [], [], [], None
    for s in range(config.streets):
        street, predicted = street_predictions(config, s, model, library, device)
        first = first or (street, predicted)
        true = street_ratios(street)
        per_street.append(accuracy(true, predicted, config.max_m, config.top_l))
        trues.append(true), preds.append(predicted)
        streets.append({"true": true.tolist(), "predicted": predicted.tolist()})
        log.info("street %d of %d: acc(1, 1) %.2f", s + 1, config.streets, per_street[-1][0, 0])
    acc = np.mean(per_street, axis=0)
    return {
        "format": "cuboid-fit/localization-experiment", "version": 1,
        "settings": asdict(config) | {"checkpoints": list(checkpoints or []),
                                       "model": None if model is None else {"shape": model.shape, "size": model.size}},
        "m": list(range(1, config.max_m + 1)), "l": list(range(1, config.top_l + 1)),
        "acc": acc.tolist(),
        "acc_per_street": [a.tolist() for a in per_street],
        "first_m_at_half": first_m_reaching(acc),
        "ratio_error": ratio_errors(np.concatenate(trues), np.concatenate(preds)),
        "example": example(config, *first),
        "streets": streets,
    }



def mask_sequence(option_values: list[str], arguments: list[str]) -> list[str]:
    """The masks in street order from `--masks A B C` (click takes A as the option's value
    and B C as arguments) or `--masks A --masks B` or plain arguments; mixing repeated
    --masks with extra arguments has no clear order and is refused."""
    option_values, arguments = list(option_values or []), list(arguments or [])
    if len(option_values) > 1 and arguments:
        raise ValueError(f"masks {option_values + arguments}: give them as --masks A B C (in street order) "
                         f"or each after its own --masks, not both")
    return option_values + arguments
