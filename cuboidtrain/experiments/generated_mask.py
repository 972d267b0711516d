"""One generated mask and its truth, for the page's "draw a generated one" (`cuboidtrain serve`).

The sample is drawn as `cuboidgen run` draws one (`make_sample`: a random view, framing,
occluders and contour noise of the scene) and handed over as `cuboidgen masks` writes it:
the input mask as 0/255 PNG bytes and the JSON of its truth (`export_masks.truth`: shape,
keypoints in the mask's pixels, ratios, the camera that framed it). Beside it, the same
truth typed for scoring a fit (`geometry.accuracy.Truth`). The page fits the PNG bytes as
any upload, so the fit never knows the mask was drawn here.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from cuboidgen.config import SCENES
from cuboidgen.export_masks import truth as truth_json
from cuboidgen.occluders import OccluderLibrary
from cuboidgen.synth import make_sample
from cuboidtrain.geometry.accuracy import Truth
from shared.checks import check_choice
from shared.errors import UsageError

GENERATED_SHAPES = ("box", "twobox", "mix")  # mix: the seed picks box or twobox
MASK_SIZES = (64, 128, 256, 512)  # px: the spool sizes the generator is run at


@dataclass(frozen=True)
class GeneratedMask:
    """A drawn sample as a file to fit, with what it was drawn as."""

    png: bytes  # the input mask (noisy, occluded), 0/255
    truth: dict  # `cuboidgen masks`' JSON beside it
    scored: Truth  # the same truth, typed for `accuracy.against_truth`


@lru_cache(maxsize=1)
def occluders() -> OccluderLibrary:
    """The generator's built-in occluders (drawn once a process)."""
    return OccluderLibrary.builtin()


def draw_generated(shape: str = "mix", scene: str = "paper", size: int = 256, seed: int = 0) -> GeneratedMask:
    """Sample `seed` of `scene` at `size` px, as `cuboidgen run --scene SCENE --size SIZE` draws it;
    a bad choice is a one-line UsageError naming the allowed ones."""
    check_choice("shape", shape, GENERATED_SHAPES)
    check_choice("scene", scene, tuple(SCENES))
    if size not in MASK_SIZES:
        raise UsageError(f"size {size!r}: expected one of {', '.join(map(str, MASK_SIZES))} px")
    if not 0 <= seed < 2**31:
        raise UsageError(f"seed {seed!r}: expected a whole number from 0 to {2**31 - 1}")
    sample = make_sample(shape, SCENES[scene], size, seed, occluders())
    ok, png = cv2.imencode(".png", np.where(sample.noisy, 255, 0).astype(np.uint8))
    if not ok:
        raise OSError("cannot encode the generated mask as PNG")
    name = f"generated-{scene}-{sample.shape}-{seed}"
    return GeneratedMask(png.tobytes(), truth_json(sample, name, f"{name}.png"), Truth.of_sample(sample))
