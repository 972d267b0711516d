"""The camera a photo already knows: its EXIF focal length, as a loose prior on a mask's camera.

Most photos carry their focal length: `FocalLengthIn35mmFilm` (the 35 mm equivalent, taken here
along the diagonal, 43.27 mm on a 36 x 24 mm frame), or `FocalLength` in mm with the sensor's
`FocalPlaneXResolution` (px per inch, cm or mm). In the mask's pixels it is:

* the mask is the photo's whole frame, at its size or resized (the same aspect, within 1%): the
  focal length scaled by mask width / photo width, the principal point at the frame's centre;
* any other mask is taken for a crop at the photo's scale: the focal length as it is, the
  principal point unknown (where the crop's corner lay is not recorded), so it is fitted, kept
  plausible as without a photo.

Either way the fit holds it loosely (`intrinsics.EXIF_FOCAL_SD`): EXIF is rounded to whole mm,
and knows nothing of a crop or a digital zoom. `--focal-px`, `--principal-px` and `--camera`
override it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from cuboidtrain.geometry.intrinsics import EXIF_FOCAL_SD, EXIF_PRINCIPAL_SIDES, KnownCamera
from shared.errors import UsageError

FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)  # what a 35 mm equivalent focal length is relative to
MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # FocalPlaneResolutionUnit: inch, cm, mm, um
ASPECT_TOLERANCE = 0.01  # a resize's rounding: the mask is the photo's whole frame within this


@dataclass(frozen=True)
class PhotoCamera:
    """A photo's focal length in its own pixels, from EXIF, and the photo's size as seen (an EXIF
    rotation applied)."""

    photo: str
    focal_px: float
    size: tuple[int, int]  # (width, height) px
    how: str  # which EXIF fields said it, for the log

    def in_frame(self, frame: tuple[int, int]) -> KnownCamera:
        """The camera in the pixels of a mask of shape `frame` (H, W) cut from this photo, as a loose
        prior: the whole frame resized (principal point at its centre), else a crop (principal fitted)."""
        height, width = frame
        photo_width, photo_height = self.size
        whole = abs(width / height - photo_width / photo_height) <= ASPECT_TOLERANCE * photo_width / photo_height
        scale = width / photo_width if whole else 1.0
        principal = ((width - 1) / 2, (height - 1) / 2) if whole else None
        return KnownCamera(self.focal_px * scale, principal, stiffness=1 / EXIF_FOCAL_SD,
                           principal_stiffness=1 / (EXIF_PRINCIPAL_SIDES * max(frame)),
                           exif=("focal_px", "principal_px") if whole else ("focal_px",))


def read_photo_camera(photo: str | Path) -> PhotoCamera | None:
    """The photo's camera from its EXIF, or None where it says no focal length; a UsageError
    naming a photo that cannot be read."""
    from PIL import ExifTags, Image, UnidentifiedImageError

    try:
        with Image.open(photo) as image:
            size, exif = image.size, image.getexif()
    except (OSError, UnidentifiedImageError) as exc:
        raise UsageError(f"--photo {photo}: cannot read it ({getattr(exc, 'strerror', None) or exc})") from None
    if exif.get(ExifTags.Base.Orientation) in (5, 6, 7, 8):  # stored on its side: seen (and masked) turned
        size = size[::-1]
    fields = exif.get_ifd(ExifTags.IFD.Exif)
    equivalent = _number(fields.get(ExifTags.Base.FocalLengthIn35mmFilm))
    if equivalent:
        return PhotoCamera(str(photo), equivalent * math.hypot(*size) / FULL_FRAME_DIAGONAL_MM, size,
                           f"35 mm equivalent {equivalent:g} mm")
    focal_mm = _number(fields.get(ExifTags.Base.FocalLength))
    per_unit = _number(fields.get(ExifTags.Base.FocalPlaneXResolution))
    unit = MM_PER_UNIT.get(fields.get(ExifTags.Base.FocalPlaneResolutionUnit, 2))
    if focal_mm and per_unit and unit:
        return PhotoCamera(str(photo), focal_mm * per_unit / unit, size,
                           f"{focal_mm:g} mm at {per_unit / unit:g} px/mm")
    return None


def _number(value) -> float | None:
    """An EXIF rational or integer as a positive finite float, else None (absent, 0, or garbled)."""
    try:
        number = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if math.isfinite(number) and number > 0 else None
