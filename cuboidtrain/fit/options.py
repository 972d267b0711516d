"""FitOptions: everything a fit may be asked, each default and each check stated once.

`infer`, `eval`, `report` and `localize` (and the Python API, `cuboidtrain.Fitter`)
take one FitOptions; `validate()` turns what a user typed (`"auto"`, `"0.999"`)
into checked values, before any input is read. No torch here: the command line
builds its choices from these lists, and `--help` must not wait for torch.
"""
from __future__ import annotations

import numbers
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import PurePath

from cuboidtrain.fit.exif import PhotoCamera
from cuboidtrain.geometry.intrinsics import KnownCamera
from cuboidtrain.models.settings import (DEFAULT_PDM_COMPONENTS, EXTRACTORS, MAX_REFINE_STEPS, check_device,
                                         parse_components)
from shared.checks import check_choice, check_numbers, number
from shared.errors import UsageError
from shared.shapes import SHAPES

FIT_SHAPES = ("auto", *SHAPES)  # auto: every model given, the best-explained fit wins
OPTIMIZERS = ("lm", "soft")  # the cuboid fit's: mask_fit (Levenberg-Marquardt), soft_mask_fit (L-BFGS)
DEFAULT_MARGIN = 0.1  # empty border around a framed object, a fraction of the model size per side


def with_exif(given: KnownCamera, exif: KnownCamera) -> KnownCamera:
    """What the user gave, held, and what they did not, from a photo's EXIF, loosely."""
    focal, principal = given.focal_px is None, given.principal_px is None  # taken from EXIF
    return KnownCamera(exif.focal_px if focal else given.focal_px,
                       exif.principal_px if principal else given.principal_px,
                       stiffness=exif.stiffness if focal else given.stiffness,
                       principal_stiffness=exif.principal_stiffness if principal else given.principal_stiffness
                       if given.principal_stiffness is not None else given.stiffness,
                       exif=tuple(n for n in exif.exif if {"focal_px": focal, "principal_px": principal}[n]))


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
    # What the object is in an image that is not a two-valued mask (masks.to_mask): the levels above T,
    # in the image's own units (0-255 for 8 bits); invert: the other side (a dark object on light).
    threshold: float | None = number(None, lo=0, optional=True, unit="a level in the image's own units")
    invert: bool = False
    device: str = "auto"  # auto (CUDA when present), cpu, cuda or cuda:N
    cuboid: bool = False  # fit a perspective cuboid to the mask at the input's resolution (cuboidtrain.fit.cuboid)
    optimizer: str = "lm"  # the cuboid fit's: lm (fast) or soft (more accurate, ~35x slower; BENCHMARKS.md)
    # The camera, where known (cuboid fit): held by the fit, which the record says (docs/contract.md).
    focal_px: float | None = number(None, lo=0, lo_open=True, optional=True)  # every input's focal length, px
    principal_px: tuple[float, float] | None = None  # every input's principal point (x, y), px
    cameras: tuple[tuple[str, KnownCamera], ...] = ()  # per input (its path as given, or its file name): --camera FILE
    photos: tuple[tuple[str, PhotoCamera], ...] = ()  # per input (its path as given): its photo's EXIF camera, --photo
    plausible_camera: bool = True  # a fitted camera kept plausible (geometry.intrinsics.PlausibleRows)
    # With the cuboid fit and both classes: on a rough mask the shipped shape classifier calls the class
    # (cuboidtrain.fit.shape_call); off, or on a clean mask, the fitted cuboids' silhouettes do.
    shape_classifier: bool = True
    # Its file; None: the models folder's (`zoo.classifier_path`). `infer` pins it before work leaves this
    # process, so that a cluster's workers load the file this machine has, as they do its box and twobox.
    classifier_file: str | None = None

    def validate(self) -> "FitOptions":
        """The checked options, strings parsed; a ValueError names the bad value and what was expected.
        Every option is checked, used or not: a typo is never silent."""
        check_choice("--shape", self.shape, FIT_SHAPES)
        check_choice("--extractor", self.extractor, EXTRACTORS)
        check_choice("--optimizer", self.optimizer, OPTIMIZERS)
        if self.optimizer != "lm" and not self.cuboid:
            raise UsageError(f"--optimizer {self.optimizer} with --networks-only: expected the cuboid fit "
                             f"(the optimizer is the cuboid fit's)")
        check_numbers(self)  # margin, label_id, focal_px: finite and in their declared ranges
        if self.label_id is not None and (self.threshold is not None or self.invert):
            given = f"--threshold {self.threshold:g}" if self.threshold is not None else "--invert"
            raise UsageError(f"{given} with --label-id {self.label_id}: expected one of them (a label map's "
                             f"object is its label's pixels, not a side of a threshold)")
        self._check_camera()
        return replace(self, refine_steps=parse_refine_steps(self.refine_steps),
                       pdm_components=parse_components(self.pdm_components), device=check_device(self.device))

    def _check_camera(self) -> None:
        principal = self.principal_px
        try:
            KnownCamera(principal_px=principal)
        except ValueError:
            raise UsageError(f"--principal-px {principal!r}: expected two finite numbers X Y (px)") from None
        given = ("--focal-px" if self.focal_px is not None else "--principal-px" if principal is not None
                 else "--camera" if self.cameras else "--photo" if self.photos else None)
        if given is not None and self.optimizer != "lm":
            raise UsageError(f"{given} with --optimizer {self.optimizer}: expected --optimizer lm (only the LM fit "
                             f"holds a given camera)")
        if given is not None and not self.cuboid:
            raise UsageError(f"{given} with --networks-only: expected the cuboid fit (the camera is the cuboid's)")

    def camera_for(self, name: str | None, frame: tuple[int, int]) -> KnownCamera | None:
        """What is known of the camera of input `name` (its entry in `cameras`, by the path as given or
        its file name, over `focal_px` / `principal_px`, over its photo's EXIF in `photos`), None if
        nothing. A full frame (`label_id` or `all_components`: the whole photo) has its principal
        point at the frame's centre unless given. What EXIF gives is a loose prior (`exif.PhotoCamera`)."""
        table = self._camera_table
        entry = table.get(name) or table.get(PurePath(name).name if name else None)
        focal = entry.focal_px if entry is not None and entry.focal_px is not None else self.focal_px
        principal = entry.principal_px if entry is not None and entry.principal_px is not None else self.principal_px
        if principal is None and (self.label_id is not None or self.all_components):
            principal = ((frame[1] - 1) / 2, (frame[0] - 1) / 2)
        photo = self._photo_table.get(name)
        if photo is not None and (focal is None or principal is None):
            return with_exif(KnownCamera.of(focal, principal), photo.in_frame(frame))
        if focal is None and principal is None:
            return None
        return KnownCamera.of(focal, principal)

    def check_cameras_match(self, inputs: list[str]) -> None:
        """Every `cameras` entry names one of the run's inputs, by its path as given or its file name
        (`camera_for`'s lookup): an entry that names none is a typo or a stale file, and its input
        would be fitted camera-free with nothing said. A one-line UsageError naming it."""
        names = set(inputs) | {PurePath(path).name for path in inputs}
        unmatched = [name for name, _ in self.cameras if name not in names]
        if unmatched:
            others = f" (and {len(unmatched) - 1} other entries)" if len(unmatched) > 1 else ""
            raise UsageError(f"--camera: {unmatched[0]!r}{others} matches no input; expected each entry to be "
                             f"an input's path as given or its file name")

    @cached_property
    def _photo_table(self) -> dict[str, PhotoCamera]:
        return dict(self.photos)

    @cached_property
    def _camera_table(self) -> dict[str, KnownCamera]:
        """`cameras` as a lookup: built once, not once an input (a city's file maps thousands)."""
        return dict(self.cameras)

    @property
    def shapes(self) -> tuple[str, ...]:
        """The shape classes whose models this fit may use."""
        return tuple(SHAPES) if self.shape == "auto" else (self.shape,)
