"""The occluder library (paper 3.3.1): the predefined set of cutouts a sample's occluders are
chosen from, either the built-in drawn urban elements or a folder of PNG cutouts.

Every mask is a tight-cropped, upright 0/1 uint8 array whose bottom row is the ground
contact, so the generator (`cuboidgen.occlusion`) can scale, flip and place it freely.
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from cuboidgen.occluders.urban_elements import KINDS, draw_element, tight_crop
from shared.errors import UsageError
from shared.files import TMP_PREFIX

# The package's one logger name, as before it was split into modules: log settings and tests name it.
log = logging.getLogger("cuboidgen.occluders")


def _foreground(img: np.ndarray) -> np.ndarray:
    """Binary mask of a cut-out: alpha where there is one, else brightness."""
    if img.ndim == 3 and img.shape[2] in (2, 4):
        plane = img[..., -1]
    elif img.ndim == 3 and img.shape[2] == 3:
        plane = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    else:
        plane = img.reshape(img.shape[:2])
    thr = np.iinfo(plane.dtype).max / 2 if plane.dtype.kind in "ui" else 0.5  # 127 for 8 bit
    return (plane > thr).astype(np.uint8)


def _read_cutout(p: Path) -> np.ndarray | None:
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    mask = None if img is None or img.size == 0 else tight_crop(_foreground(img))
    if mask is None:  # one bad file should not cost the whole library
        why = "not readable as an image" if img is None else "no foreground (alpha or gray > 127)"
        log.warning("occluder %s: %s; skipped", p, why)
    return mask


class OccluderLibrary:
    """Tight-cropped upright 0/1 occluder masks with one name (kind) each."""

    def __init__(self, masks: list[np.ndarray], names: list[str], source: str):
        self.masks, self.names, self.source = masks, names, source

    def __len__(self) -> int:
        return len(self.masks)

    @classmethod
    def builtin(cls, variants_per_kind: int = 16, seed: int = 0) -> "OccluderLibrary":
        rng = np.random.default_rng(seed)
        masks = [draw_element(k, rng, rng.uniform(96, 160), i) for k in KINDS for i in range(variants_per_kind)]
        return cls(masks, [k for k in KINDS for _ in range(variants_per_kind)], "builtin")

    @classmethod
    def from_dir(cls, path) -> "OccluderLibrary":
        folder = Path(path)
        if not folder.is_dir():
            raise UsageError(f"occluders folder {folder}: no such folder")
        files = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() == ".png"
                        and not p.name.startswith(TMP_PREFIX)),
                       key=lambda p: p.name)
        if not files:
            raise UsageError(f"occluders folder {folder}: no PNG files (expected RGBA or binary PNG cutouts)")
        loaded = [(p.stem, m) for p in files if (m := _read_cutout(p)) is not None]
        if not loaded:
            raise UsageError(f"occluders folder {folder}: none of its {len(files)} PNG files is usable "
                             "(expected RGBA or binary PNG cutouts with some foreground)")
        log.info("loaded %d occluders from %s", len(loaded), folder)
        return cls([m for _, m in loaded], [n for n, _ in loaded], str(folder))

    @classmethod
    def load(cls, path=None) -> "OccluderLibrary":
        return cls.builtin() if path is None else cls.from_dir(path)
