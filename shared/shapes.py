"""Shape definitions: keypoint tables, parts, wireframe edges and ratios.

Keypoints are named in viewer terms (docs/contract.md, "Viewer terms"): FRONT faces the camera, LEFT is
image-left, TOP is up. Every part of a shape is a box whose eight corners are
listed in Table 1 order, so one set of box rules (edges, extents) serves both
shapes; `twobox` only maps its parts' corners onto Table 2 indices.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from shared.errors import UsageError

DEPTHS = ("BACK", "FRONT")
WIDTHS = ("RIGHT", "LEFT")
HEIGHTS = ("TOP", "BOTTOM")

# Table 1 order is binary: corner = 4 * front + 2 * left + bottom.
BOX_CORNERS = tuple(f"{d}-{w}-{h}" for d in DEPTHS for w in WIDTHS for h in HEIGHTS)
# Corners of one box that differ in exactly one of (bottom, left, front) share an edge.
BOX_EDGES = tuple((c, c ^ bit) for c in range(8) for bit in (1, 2, 4) if c < c ^ bit)
# Corner pairs spanning each dimension of a box, in Table 1 corner indices.
BOX_HEIGHT_EDGE, BOX_WIDTH_EDGE, BOX_DEPTH_EDGE = (0, 1), (0, 2), (0, 4)

RATIO_KEYS = ("depth_height", "width_height")


@dataclass(frozen=True)
class Shape:
    """A shape class: named keypoints and the boxes (parts) they form."""

    name: str
    keypoint_names: tuple[str, ...]
    part_names: tuple[str, ...]
    parts: tuple[tuple[int, ...], ...]  # each part's 8 keypoint indices, in Table 1 corner order

    @property
    def num_keypoints(self) -> int:
        return len(self.keypoint_names)

    @cached_property
    def edges(self) -> tuple[tuple[int, int], ...]:
        """Wireframe edges as keypoint index pairs, without repeats."""
        seen: dict[tuple[int, int], None] = {}
        for part in self.parts:
            for a, b in BOX_EDGES:
                seen[tuple(sorted((part[a], part[b])))] = None
        return tuple(seen)

    @cached_property
    def ratio_names(self) -> tuple[str, ...]:
        """Flat names of the ratio vector, e.g. `right.depth_height` for twobox."""
        if len(self.parts) == 1:
            return RATIO_KEYS
        return tuple(f"{p}.{k}" for p in self.part_names for k in RATIO_KEYS)

    @cached_property
    def mirror_left_right(self) -> np.ndarray:
        """Index permutation that relabels keypoints after an image-left/right swap."""
        swap = {"RIGHT": "LEFT", "LEFT": "RIGHT", "(R)": "(L)", "(L)": "(R)"}
        return self._permutation(swap)

    @cached_property
    def mirror_front_back(self) -> np.ndarray:
        """Index permutation that relabels keypoints after a front/back swap."""
        return self._permutation({"FRONT": "BACK", "BACK": "FRONT"})

    def _permutation(self, swap: dict[str, str]) -> np.ndarray:
        index = {name: i for i, name in enumerate(self.keypoint_names)}
        pattern = re.compile("|".join(re.escape(word) for word in swap))
        renamed = (pattern.sub(lambda m: swap[m.group(0)], n) for n in self.keypoint_names)
        return np.array([index[n] for n in renamed], dtype=np.intp)

    def having(self, word: str) -> np.ndarray:
        """Indices of the keypoints whose name contains `word` (e.g. FRONT, LEFT)."""
        return np.array([i for i, n in enumerate(self.keypoint_names) if word in n], dtype=np.intp)

    def ratios(self, points3d: np.ndarray) -> dict:
        """Depth/height and width/height of each part from its 3D corners (any rigid pose)."""
        per_part, points = {}, points3d.tolist()
        for name, part in zip(self.part_names, self.parts):
            height, width, depth = (
                math.dist(points[part[a]], points[part[b]])
                for a, b in (BOX_HEIGHT_EDGE, BOX_WIDTH_EDGE, BOX_DEPTH_EDGE)
            )
            per_part[name] = {"depth_height": depth / height, "width_height": width / height}
        return per_part[self.part_names[0]] if len(self.parts) == 1 else per_part

    def ratio_vector(self, ratios: dict) -> np.ndarray:
        """The nested ratio record flattened in `ratio_names` order."""
        if len(self.parts) == 1:
            return np.array([ratios[k] for k in RATIO_KEYS], dtype=np.float64)
        return np.array([ratios[p][k] for p in self.part_names for k in RATIO_KEYS], dtype=np.float64)

    def ratio_dict(self, vector) -> dict:
        """Inverse of `ratio_vector`: the nested record samples and infer records use (docs/contract.md, "Ratios")."""
        values = [float(v) for v in vector]
        if len(self.parts) == 1:
            return dict(zip(RATIO_KEYS, values))
        return {
            p: dict(zip(RATIO_KEYS, values[2 * i : 2 * i + 2])) for i, p in enumerate(self.part_names)
        }


BOX = Shape(name="box", keypoint_names=BOX_CORNERS, part_names=("box",), parts=(tuple(range(8)),))

# Table 2: the right-hand box keeps indices 0-7 with MIDDLE in place of LEFT and
# TOP(R) for its top; the left-hand box adds 8-13 and shares the bottom edge 3-7.
TWOBOX = Shape(
    name="twobox",
    keypoint_names=(
        "BACK-RIGHT-TOP(R)", "BACK-RIGHT-BOTTOM", "BACK-MIDDLE-TOP(R)", "BACK-MIDDLE-BOTTOM",
        "FRONT-RIGHT-TOP(R)", "FRONT-RIGHT-BOTTOM", "FRONT-MIDDLE-TOP(R)", "FRONT-MIDDLE-BOTTOM",
        "BACK-MIDDLE-TOP(L)", "BACK-LEFT-TOP(L)", "BACK-LEFT-BOTTOM",
        "FRONT-MIDDLE-TOP(L)", "FRONT-LEFT-TOP(L)", "FRONT-LEFT-BOTTOM",
    ),
    part_names=("right", "left"),
    # The left box in Table 1 corner order: its RIGHT side is the MIDDLE wall.
    parts=(tuple(range(8)), (8, 3, 9, 10, 11, 7, 12, 13)),
)

SHAPES: dict[str, Shape] = {s.name: s for s in (BOX, TWOBOX)}


def get_shape(name: str) -> Shape:
    """The shape called `name`; a clear error names the allowed ones."""
    try:
        return SHAPES[name]
    except KeyError:
        raise UsageError(f"unknown shape {name!r}: expected one of {sorted(SHAPES)}") from None
