"""FitOptions: everything a fit may be asked, each default and each check stated once.

`infer`, `eval`, `report` and `localize` (and the Python API, `cuboidtrain.Fitter`)
take one FitOptions; `validate()` turns what a user typed (`"auto"`, `"0.999"`)
into checked values, before any input is read. No torch here: the command line
builds its choices from these lists, and `--help` must not wait for torch.
"""
from __future__ import annotations

import numbers
from dataclasses import dataclass, replace

from cuboidtrain.models.settings import (DEFAULT_PDM_COMPONENTS, EXTRACTORS, MAX_REFINE_STEPS, check_device,
                                         parse_components)
from shared.checks import check_choice, check_numbers, number
from shared.errors import UsageError
from shared.shapes import SHAPES

FIT_SHAPES = ("auto", *SHAPES)  # auto: every model given, the best-explained fit wins
OPTIMIZERS = ("lm", "soft")  # the cuboid fit's: mask_fit (Levenberg-Marquardt), soft_raster (L-BFGS)
DEFAULT_MARGIN = 0.1  # empty border around a framed object, a fraction of the model size per side


def parse_refine_steps(value: int | str | None, allow_auto: bool = True) -> int | None:
    """`auto` (or None) -> None: until the Refiner settles; otherwise a count of passes, 0 to
    MAX_REFINE_STEPS (auto's own cap: a pass more than auto would ever run is never wanted).
    An exported graph runs a fixed number of passes: it does not `allow_auto`."""
    if allow_auto and (value is None or value == "auto"):
        return None
    steps = -1
    if isinstance(value, str) and value.strip().isascii() and value.strip().isdigit():
        steps = int(value)
    elif isinstance(value, numbers.Integral) and not isinstance(value, bool):
        steps = int(value)
    elif isinstance(value, float) and value.is_integer():
        steps = int(value)
    if not 0 <= steps <= MAX_REFINE_STEPS:
        raise UsageError(f"--refine-steps {value!r}: expected a whole number of passes from 0 to {MAX_REFINE_STEPS}"
                         + (" or auto" if allow_auto else ""))
    return steps


@dataclass(frozen=True)
class FitOptions:
    shape: str = "auto"  # a FIT_SHAPES name: which models may fit
    refine_steps: int | str | None = 1  # Refiner passes; None or "auto": until a pass changes nothing
    margin: float = number(DEFAULT_MARGIN, lo=0, hi=0.5, hi_open=True)  # a fraction of the model size per side
    extractor: str = "tabulator"  # how keypoints are read off the heat maps; ratios are always T's
    pdm_components: int | float | str = DEFAULT_PDM_COMPONENTS  # with extractor "pdm": a count or a fraction
    all_components: bool = False  # one fit per 8-connected component (>= 16 px), else one building (masks.silhouette)
    label_id: int | None = number(None, lo=0, hi=65535, integer=True, optional=True)  # read a grey label map: pixels equal to this id are the object
    device: str = "auto"  # auto (CUDA when present), cpu, cuda or cuda:N
    cuboid: bool = False  # fit a perspective cuboid to the mask at the input's resolution (cuboidtrain.fit.cuboid)
    optimizer: str = "lm"  # the cuboid fit's: lm (fast) or soft (more accurate, ~35x slower; BENCHMARKS.md)

    def validate(self) -> "FitOptions":
        """The checked options, strings parsed; a ValueError names the bad value and what was expected.
        Every option is checked, used or not: a typo is never silent."""
        check_choice("--shape", self.shape, FIT_SHAPES)
        check_choice("--extractor", self.extractor, EXTRACTORS)
        check_choice("--optimizer", self.optimizer, OPTIMIZERS)
        if self.optimizer != "lm" and not self.cuboid:
            raise UsageError(f"--optimizer {self.optimizer} with --networks-only: expected the cuboid fit "
                             f"(the optimizer is the cuboid fit's)")
        check_numbers(self)  # margin, label_id: finite and in their declared ranges
        return replace(self, refine_steps=parse_refine_steps(self.refine_steps),
                       pdm_components=parse_components(self.pdm_components), device=check_device(self.device))

    @property
    def shapes(self) -> tuple[str, ...]:
        """The shape classes whose models this fit may use."""
        return tuple(SHAPES) if self.shape == "auto" else (self.shape,)
