"""What the networks may be asked, without torch: extractor names, the Refiner's cap, PDM components, devices.

The command line builds its choices from these (its `--help` must not wait for torch), and
FitOptions and TrainConfig check their values against them.
"""
from __future__ import annotations

import math
import re

from shared.errors import UsageError

EXTRACTORS = ("tabulator", "argmax", "centre-of-mass", "dark", "pdm")  # cuboidtrain.models.codec.CODECS
MAX_REFINE_STEPS = 16  # "auto" stops here even if the Refiner never settles
DEFAULT_PDM_COMPONENTS = 0.999  # of shape variance: 9 of the box's 16 components, 0.2 px from exact at 64 px


def check_device(device) -> str:
    """A device name torch may take: auto (CUDA when present), cpu, cuda or cuda:N (whether CUDA
    is there is `cuboidtrain.models.device.resolve_device`'s to say, when a model moves)."""
    name = str(device)
    if name not in ("auto", "cpu", "cuda") and not re.fullmatch(r"cuda:\d+", name):
        raise UsageError(f"--device {device!r}: expected auto, cpu, cuda or cuda:N")
    return name


def parse_components(value: str | int | float) -> int | float:
    """`--pdm-components`: an integer count (>= 1) or a variance fraction in (0, 1)."""
    text = str(value).strip()
    try:
        parsed = float(text)
    except ValueError:
        parsed = math.nan
    if not math.isfinite(parsed):
        parsed = math.nan
    if parsed >= 1 and parsed == int(parsed) and "." not in text:
        return int(parsed)
    if 0 < parsed < 1:
        return parsed
    raise UsageError(f"--pdm-components {value!r}: expected a count of components (1, 2, ...) "
                     f"or a fraction of the shape variance to keep, between 0 and 1")
