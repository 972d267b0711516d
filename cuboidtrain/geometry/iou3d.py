"""The 3D IoU of oriented boxes (Objectron's measure), and of solids made of disjoint boxes.

Objectron (Ahmadyan et al., CVPR 2021) scores a 3D box by the exact IoU of two oriented
boxes: objectron/dataset/iou.py (github.com/google-research-datasets/Objectron) clips each
box's faces by the other box's planes (Sutherland-Hodgman), keeps the clipped polygons'
vertices, which are the vertices of the intersection, and takes the volume of their convex
hull (scipy's ConvexHull). The same clipping here, in numpy alone; the volume is then taken
from the clipped polygons themselves, which are the intersection's faces (see
`intersection_volume`), rather than from a convex hull of their vertices.

A twobox is two boxes sharing a wall, disjoint but for it: `union_iou` sums the pairwise
intersections, IoU = I / (V1 + V2 - I).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Corner i of a box has bit 0 for its x side, bit 1 for y, bit 2 for z (0: the - side).
_SIGNS = np.array([[(i >> a) & 1 for a in range(3)] for i in range(8)], dtype=np.float64) - 0.5
# Each face as 4 corner indices in cyclic order: the axis it holds at one side, the other two walked round.
_FACES = np.array([[(side << axis) | (bu << u) | (bv << v) for bu, bv in ((0, 0), (1, 0), (1, 1), (0, 1))]
                   for axis, u, v in ((0, 1, 2), (1, 2, 0), (2, 0, 1)) for side in (0, 1)])
# Table 1's corner order (shared.shapes): index = 4 * FRONT + 2 * LEFT + BOTTOM.
_TABLE1_LEFT, _TABLE1_BOTTOM, _TABLE1_FRONT = (np.array([(c >> b) & 1 for c in range(8)], dtype=bool) for b in (1, 0, 2))
RELATIVE_TOLERANCE = 1e-9  # of the boxes' scale: the slack that makes coplanar faces count once


@dataclass(frozen=True)
class OrientedBox:
    """A box anywhere: its centre, its axes (the columns of `axes`, orthonormal) and its full
    extent along each axis."""

    centre: np.ndarray  # (3,)
    axes: np.ndarray  # (3, 3), column a is the unit vector of the box's axis a
    size: np.ndarray  # (3,)

    @classmethod
    def from_corners(cls, corners: np.ndarray) -> OrientedBox:
        """A box from its 8 corners (8, 3) in Table 1's order (shared.shapes: 4 * FRONT + 2 * LEFT
        + BOTTOM): its x axis toward RIGHT, y toward BOTTOM, z toward BACK."""
        c = np.asarray(corners, dtype=np.float64)
        edges = np.stack([c[~_TABLE1_LEFT].mean(0) - c[_TABLE1_LEFT].mean(0),
                          c[_TABLE1_BOTTOM].mean(0) - c[~_TABLE1_BOTTOM].mean(0),
                          c[~_TABLE1_FRONT].mean(0) - c[_TABLE1_FRONT].mean(0)], axis=1)
        size = np.linalg.norm(edges, axis=0)
        return cls(c.mean(0), edges / np.where(size > 0, size, 1.0), size)

    def corners(self) -> np.ndarray:
        """(8, 3); corner i takes the + side of axis a where bit a of i is set."""
        return self.centre + (_SIGNS * self.size) @ self.axes.T

    @property
    def volume(self) -> float:
        return float(np.prod(self.size))

    def scaled(self, factor: float) -> OrientedBox:
        """The box scaled by `factor` about the origin (a camera's centre: the same picture)."""
        return OrientedBox(self.centre * factor, self.axes, self.size * factor)

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> OrientedBox:
        """The box moved rigidly: x -> rotation @ x + translation."""
        return OrientedBox(rotation @ self.centre + translation, rotation @ self.axes, self.size)

    def planes(self) -> tuple[np.ndarray, np.ndarray]:
        """Outward normals (6, 3) and offsets (6,): the inside is normals @ x <= offsets."""
        normals = np.concatenate([-self.axes.T, self.axes.T])
        offsets = normals @ self.centre + np.tile(self.size / 2, 2)
        return normals, offsets

    def faces(self) -> np.ndarray:
        """(6, 4, 3) the faces as polygons."""
        return self.corners()[_FACES]


def _clip(polygon: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """Sutherland-Hodgman: the part of a convex polygon (M, 3), vertices in cyclic order, where
    normal @ x <= offset, still in cyclic order."""
    if not len(polygon):
        return polygon
    distance = polygon @ normal - offset
    inside = distance <= 0
    out = []
    for i in range(len(polygon)):
        j = (i + 1) % len(polygon)
        if inside[i]:
            out.append(polygon[i])
        if inside[i] != inside[j]:
            t = distance[i] / (distance[i] - distance[j])
            out.append(polygon[i] + t * (polygon[j] - polygon[i]))
    return np.array(out).reshape(-1, 3)


def _clipped_faces(box: OrientedBox, other: OrientedBox, slack: float) -> list[np.ndarray]:
    """Each face of `box` clipped by every plane of `other`, moved outward by `slack`."""
    normals, offsets = other.planes()
    faces = []
    for face in box.faces():
        for normal, offset in zip(normals, offsets):
            face = _clip(face, normal, offset + slack)
        faces.append(face)
    return faces


def intersection_volume(a: OrientedBox, b: OrientedBox) -> float:
    """The volume common to two boxes (exact up to rounding).

    The intersection's surface is the part of a's surface inside b and the part of b's inside a:
    a's faces clipped by b's planes, b's clipped by a's. A face of b that lies on a face of a
    would count twice: b's faces are clipped a hair inside a's planes (and a's a hair outside
    b's), so a coplanar piece counts once, as a's. The volume is then the sum of the pyramids from
    the surface points' centroid (inside the intersection, which is convex) to each piece.
    """
    scale = max(float(np.abs(a.centre).max()), float(np.abs(b.centre).max()), float(a.size.max()), float(b.size.max()))
    slack = RELATIVE_TOLERANCE * max(scale, 1e-300)
    pieces = [p for p in _clipped_faces(a, b, slack) + _clipped_faces(b, a, -slack) if len(p) >= 3]
    if not pieces:
        return 0.0
    centre = np.concatenate(pieces).mean(0)
    volume = 0.0
    for piece in pieces:
        spokes = piece[1:] - piece[0]
        vector_area = 0.5 * np.cross(spokes[:-1], spokes[1:]).sum(0)  # normal * area of a planar polygon
        volume += abs(float(vector_area @ (piece[0] - centre))) / 3
    return min(volume, a.volume, b.volume)


def iou(a: OrientedBox, b: OrientedBox) -> float:
    """Intersection over union of two boxes, in [0, 1]."""
    return union_iou([a], [b])


def union_iou(a: list[OrientedBox], b: list[OrientedBox]) -> float:
    """IoU of two solids, each a union of boxes that do not overlap (a twobox's two parts):
    the pairwise intersections summed over V_a + V_b - I. 0 for two empty solids."""
    inter = sum(intersection_volume(p, q) for p in a for q in b)
    union = sum(p.volume for p in a) + sum(q.volume for q in b) - inter
    return float(inter / union) if union > 0 else 0.0
