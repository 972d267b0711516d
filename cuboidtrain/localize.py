"""Localization from sequences of building ratios (paper section 5).

A street is known building by building (width, height, depth). Photos of m
consecutive buildings give predicted ratios (depth/height, width/height) per
building; the sub-sequence of the street whose true ratios are nearest in L2
distance is where the photos were taken.

Here: the street (a JSON file), the matching (eq. 2's distances and Figure 12's
probabilities), and the practical command: a street's JSON and the user's masks,
in street order, give the ranked start positions with probabilities (softmax of
negative distances). The experiment of section 5.1 (random streets drawn by the
generator) is `cuboidtrain.experiments.localize_experiment`.

Positions are 0-based here and 1-based in what people read (tables, figures).
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from cuboidtrain.fit.fitter import Fitter, FitFailure
from cuboidtrain.models.networks import CuboidNet
from cuboidtrain.fit.options import FitOptions
from shared.errors import UsageError
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
    """A street JSON file (docs/inference.md, "Localization"); ValueError names what is wrong."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise UsageError(f"--street {path}: cannot read it ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise UsageError(f"--street {path}: not JSON ({exc})") from None
    return street_from_dict(data, source=str(path))


def street_from_dict(data, source: str = "street") -> list[Building]:
    if not isinstance(data, dict):
        raise UsageError(f"{source}: a JSON {type(data).__name__}, expected an object with format, version and buildings")
    if data.get("format") != STREET_FORMAT:
        raise UsageError(f"{source}: format {data.get('format')!r}, expected {STREET_FORMAT!r}")
    if data.get("version") != STREET_VERSION:
        raise UsageError(f"{source}: version {data.get('version')!r}, expected {STREET_VERSION}")
    buildings = data.get("buildings")
    if not isinstance(buildings, list) or not buildings:
        raise UsageError(f"{source}: buildings = {buildings!r}, expected a non-empty list of "
                         f"{{\"name\", \"width\", \"height\", \"depth\"}} objects")
    return [building_from_dict(b, f"{source}: buildings[{k}]", default_name=f"#{k + 1}")
            for k, b in enumerate(buildings)]


def building_from_dict(data, where: str, default_name: str) -> Building:
    if not isinstance(data, dict):
        raise UsageError(f"{where} = {data!r}, expected an object with width, height and depth")
    extents = {}
    for key in EXTENTS:
        if key not in data:
            raise UsageError(f"{where}: missing key {key!r} (expected width, height and depth, in any one unit)")
        value = data[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise UsageError(f"{where}.{key} = {value!r}, expected a positive number")
        extents[key] = float(value)
    name = data.get("name", default_name)
    if not isinstance(name, str):
        raise UsageError(f"{where}.name = {name!r}, expected a string")
    return Building(name=name, **extents)


def street_to_dict(street: list[Building]) -> dict:
    return {"format": STREET_FORMAT, "version": STREET_VERSION, "buildings": [asdict(b) for b in street]}


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
        raise UsageError(f"--max-m {max_m}: expected 1 to the number of buildings ({n})")
    if top_l < 1:
        raise UsageError(f"--top-l {top_l}: expected 1 or more")
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
        raise UsageError(f"{m} predicted buildings for a street of {len(true)}: expected 1 to {len(true)}")
    if not temperature > 0:
        raise UsageError(f"--temperature {temperature}: expected a positive number")
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
    raise UsageError(f"--checkpoint: localization needs a box model (a street's buildings are single boxes); "
                     f"got {', '.join(m.shape for m in models) or 'none'}")


def localize_masks(street: list[Building], masks: list[str], models: list[CuboidNet],
                   options: FitOptions | None = None, temperature: float = 1.0) -> dict:
    """The practical command: the user's masks of consecutive buildings (street order) ->
    their predicted ratios (fitted by the box model, as `infer --shape box` fits them) and
    every start position ranked by probability."""
    if len(masks) > len(street):
        raise UsageError(f"{len(masks)} masks for a street of {len(street)} buildings: "
                         f"expected at most as many masks as buildings")
    if not temperature > 0:
        raise UsageError(f"--temperature {temperature}: expected a positive number")
    options = replace(options or FitOptions(), shape="box")
    fits = Fitter([box_model(models)], options).outcomes(masks)
    for fit in fits:
        if isinstance(fit, FitFailure):
            raise UsageError(f"{fit.reason} (every mask is needed: the sequence cannot have a gap)")
    predicted = np.array([[f.ratios[k] for k in RATIO_KEYS] for f in fits])
    return {
        "format": "cuboid-fit/localization", "version": 1, "temperature": temperature,
        "masks": [{"input": f.input, "ratios": f.ratios, "confidence": f.confidence} for f in fits],
        "street": street_to_dict(street),
        "ranking": rank_starts(street, predicted, temperature),
    }


def mask_sequence(option_values: list[str], arguments: list[str]) -> list[str]:
    """The masks in street order from `--masks A B C` (click takes A as the option's value
    and B C as arguments) or `--masks A --masks B` or plain arguments; mixing repeated
    --masks with extra arguments has no clear order and is refused."""
    option_values, arguments = list(option_values or []), list(arguments or [])
    if len(option_values) > 1 and arguments:
        raise UsageError(f"masks {option_values + arguments}: give them as --masks A B C (in street order) "
                         f"or each after its own --masks, not both")
    return option_values + arguments
