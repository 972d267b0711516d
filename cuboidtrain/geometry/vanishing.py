"""The algebraic start of the lift: vanishing points of the box's parallel edges -> focal
length, principal point and rotation, then extents and translation by linear least squares.

The affine start (`cuboidtrain.geometry.lift.affine_starts`) is exact for a distant camera and
far off for a close one; this start is exact for a close one (three finite vanishing points)
and degrades as a vanishing point runs off to infinity. The lift tries both.

1. Each edge direction (width, height, depth) has 4 parallel edges (8 for twobox): its
   vanishing point is the least-squares common point of their image lines (homogeneous).
2. Three finite vanishing points of orthogonal directions fix the camera: the principal point
   is their triangle's orthocentre and f^2 = -(v1 - c).(v2 - c). With one at infinity (e.g.
   vertical edges parallel in the image) the principal point lies somewhere on the line of
   the two finite ones; with two at infinity the focal length is free (`intrinsics`): those
   give a range of candidates, ranked by the linear solve of step 4.
3. The rotation's columns are K^-1 v, up to sign: all sign choices are tried (a reflection is
   the x-mirrored box, `geometry`'s `mirror`).
4. With K and the rotation known, each corner's projection is linear in the extents and the
   translation: P = M X(theta) + T, and u P_z - P_x = 0, v P_z - P_y = 0 in normalised image
   coordinates. Height (of the RIGHT part) is 1, the scale gauge.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from cuboidtrain.geometry.camera_params import MIRROR_X, object_basis, rotation_vector
from shared.shapes import Shape

# A vanishing point whose homogeneous w is below this share of its norm (in corner-span
# units) is taken as at infinity: its lines are parallel to rounding error. Exact corners
# fix even a far vanishing point (w = 1e-4 in near-frontal `paper` views), and the three
# finite ones then give the exact camera: at 1e-3 here, 3% of exact twobox lifts failed.
INFINITE = 1e-9
# Between INFINITE and this, a vanishing point is tried both as finite and as at infinity:
# near-frontal views put it far out, where noisy corners fix it poorly.
DOUBTFUL = 0.05
LINE_STEPS = 9  # principal-point candidates on the line of two finite vanishing points
FOCAL_STEPS = 9  # focal-length candidates (x the corners' mean radius) with one finite
KEEP = 3  # the best (intrinsics, signs) by the linear solve's residual become LM starts


def _normalise(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Points centred and scaled to unit mean radius (conditioning of the line fits)."""
    centre = points.mean(0)
    gaps = points - centre
    scale = float(np.sqrt((gaps * gaps).sum(1)).mean()) or 1.0  # np.linalg.norm's arithmetic
    return (points - centre) / scale, centre, scale


def edges_by_axis(shape: Shape) -> list[list[tuple[int, int]]]:
    """The shape's edges grouped by the object axis they run along (x width, y height, z depth)."""
    groups: list[list[tuple[int, int]]] = [[], [], []]
    # A corner's index bits (`CORNER_SIDES`): 2 = LEFT, 1 = BOTTOM, 4 = FRONT; an edge flips one.
    for part in shape.parts:
        for axis, flip in ((0, 2), (1, 1), (2, 4)):
            groups[axis] += [(part[a], part[a ^ flip]) for a in range(8) if a < a ^ flip]
    return [sorted(set(g)) for g in groups]


@lru_cache(maxsize=None)
def _edge_arrays(shape: Shape) -> tuple[np.ndarray, ...]:
    """`edges_by_axis` as (E, 2) index arrays, computed once a shape."""
    arrays = tuple(np.asarray(edges) for edges in edges_by_axis(shape))
    for array in arrays:
        array.flags.writeable = False  # shared by every caller
    return arrays


def vanishing_point(points: np.ndarray, edges: list[tuple[int, int]] | np.ndarray) -> np.ndarray:
    """Homogeneous (3,) least-squares common point of the edges' lines, unit norm."""
    ends = np.asarray(edges)
    a, b = points[ends[:, 0]], points[ends[:, 1]]
    # The cross product of (a, 1) and (b, 1), as np.cross computes it (its products by 1 are exact),
    # without its wrapper: three lines a start, several starts a record.
    lines = np.stack([a[:, 1] - b[:, 1], b[:, 0] - a[:, 0], a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)
    lines /= np.sqrt((lines[:, :2] * lines[:, :2]).sum(1, keepdims=True)) + 1e-12  # np.linalg.norm's arithmetic
    return np.linalg.svd(lines)[2][-1]


def intrinsics(vps: np.ndarray, finite: np.ndarray) -> list[tuple[float, np.ndarray]]:
    """(focal, principal) candidates in normalised units from (3, 3) homogeneous vanishing
    points, `finite` (3,) saying which to take as finite.

    Three finite: the orthocentre, exact. Two: the principal point lies on their line (the
    third direction is perpendicular to it) but where is free, so positions between them are
    all candidates. One: it is the principal point if the box faces the camera squarely, and
    the focal length is free (one-point perspective trades it against depth), so a range.
    The linear solve of extents (`_extents_and_translation`) then ranks the candidates."""
    points = vps[finite, :2] / vps[finite, 2:3]
    if len(points) == 3:
        a, b, c = points
        m = np.array([b - c, a - c])  # orthocentre: (p - a).(b - c) = 0 and (p - b).(a - c) = 0
        if abs(np.linalg.det(m)) < 1e-12:
            return []
        principal = np.linalg.solve(m, np.array([a @ (b - c), b @ (a - c)]))
        f2 = -(a - principal) @ (b - principal)
        return [(float(np.sqrt(f2)), principal)] if f2 > 0 else []
    if len(points) == 2:
        a, b = points
        candidates = []
        for t in _ALONG:
            principal = a + t * (b - a)
            candidates.append((float(np.sqrt(-(a - principal) @ (b - principal))), principal))
        return candidates
    if len(points) == 1:
        return [(f, points[0]) for f in _FOCALS]
    return []


def _extents_and_translation(image: np.ndarray, m: np.ndarray, coef: np.ndarray,
                             const: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """theta (C, Q) and T (C, 3) for C candidate cameras at once: normalised image corners
    `image` (C, N, 2) (unit focal, principal point at 0) and rotations-or-reflections `m`
    (C, 3, 3); and each one's rms residual (C,). Normal equations, batched: the corners are
    normalised, so they are well conditioned."""
    c, n, _ = image.shape
    q = coef.shape[2]
    # M X's coefficients (C, N, 3, Q) and constants (C, N, 3): einsum's sums over j, written out (the same
    # products added in the same order, at two thirds of its cost), each term laid out (C, 3, N Q) so that
    # numpy's inner loops run along N Q, not Q (the same values, at half the cost), then viewed (C, N, 3, Q).
    by_axis, const_by_axis = coef.transpose(1, 0, 2).reshape(3, n * q), const.T  # [j]: coef[:, j, :], const[:, j]
    mc = (m[:, :, 0, None] * by_axis[0] + m[:, :, 1, None] * by_axis[1]
          + m[:, :, 2, None] * by_axis[2]).reshape(c, 3, n, q).transpose(0, 2, 1, 3)
    me = (m[:, :, 0, None] * const_by_axis[0] + m[:, :, 1, None] * const_by_axis[1]
          + m[:, :, 2, None] * const_by_axis[2]).transpose(0, 2, 1)
    a = np.zeros((c, n, 2, q + 3))
    a[..., :q] = image[..., None] * mc[:, :, None, 2] - mc[:, :, :2]
    a[..., 0, q], a[..., 1, q + 1] = -1.0, -1.0
    a[..., q + 2] = image
    b = -(image * me[..., 2:3] - me[..., :2])
    a, b = a.reshape(c, 2 * n, q + 3), b.reshape(c, 2 * n)
    solution = np.linalg.solve(a.transpose(0, 2, 1) @ a, np.einsum("cmk,cm->ck", a, b)[..., None])[..., 0]
    rms = np.sqrt(np.mean((np.einsum("cmk,ck->cm", a, solution) - b) ** 2, axis=1))
    return solution[:, :q], solution[:, q:], rms


def vanishing_starts(points: np.ndarray, shape: Shape, keep: int = KEEP) -> tuple[np.ndarray, np.ndarray]:
    """Start params (H <= keep, P) and mirror flags (H,) from labelled image corners (N, 2),
    in `geometry`'s layout; empty when no candidate camera gives a box in front of it."""
    unit, centre, scale = _normalise(np.asarray(points, dtype=np.float64))
    vps = np.array([vanishing_point(unit, edges) for edges in _edge_arrays(shape)])
    focals, principals, directions = [], [], []
    for finite in _finiteness_choices(np.abs(vps[:, 2])):
        directions_xy = np.where(finite[:, None], vps[:, :2] / np.where(finite, vps[:, 2], 1.0)[:, None], vps[:, :2])
        if not (candidates := intrinsics(vps, finite)):
            continue
        # Every candidate's rays at once (C, 3, 2), each the arithmetic one candidate's alone would do.
        focal, principal = np.array([f for f, _ in candidates]), np.array([c for _, c in candidates])
        rays = np.where(finite[:, None], (directions_xy - principal[:, None]) / focal[:, None, None], directions_xy)
        focals += [f for f, _ in candidates]
        principals += [c for _, c in candidates]
        directions.append(np.concatenate([rays, np.broadcast_to(finite[:, None].astype(np.float64), (len(rays), 3, 1))],
                                         axis=2))
    p = 11 if len(shape.parts) == 1 else 13
    if not focals:
        return np.zeros((0, p)), np.zeros(0, dtype=bool)
    # The nearest orthogonal matrices, all candidates in one SVD call: columns = the object axes in the camera.
    directions = np.concatenate(directions)
    lengths = np.sqrt((directions * directions).sum(2, keepdims=True))  # np.linalg.norm's arithmetic
    u, _, vt = np.linalg.svd(directions / lengths)
    bases = (u @ vt).transpose(0, 2, 1)
    # Every candidate camera times every sign choice of the axes, solved at once.
    focal = np.repeat(focals, len(_SIGNS))
    principal = np.repeat(principals, len(_SIGNS), axis=0)
    m = (bases[:, None] * _SIGNS[None, :, None, :]).reshape(-1, 3, 3)
    coef, const = object_basis(shape)
    theta, t, rms = _extents_and_translation((unit[None] - principal[:, None]) / focal[:, None, None], m, coef, const)
    camera = np.einsum("cij,cnj->cni", m, np.einsum("njq,cq->cnj", coef, theta) + const) + t[:, None]
    good = np.flatnonzero(_plausible(theta) & (camera[..., 2] > 0).all(1))
    best = good[np.argsort(rms[good] * focal[good])[:keep]]  # rms in corner-span units
    starts, mirrors = [], []
    for i in best:
        mirror = bool(np.linalg.det(m[i]) < 0)
        rot = m[i] @ MIRROR_X if mirror else m[i]
        starts.append(_to_params(theta[i], rot, t[i], focal[i] * scale, principal[i] * scale + centre, len(shape.parts)))
        mirrors.append(mirror)
    return np.array(starts).reshape(-1, p), np.array(mirrors, dtype=bool)


_FOCALS = np.geomspace(0.5, 50.0, FOCAL_STEPS).tolist()  # the focal-length candidates with one finite
_ALONG = np.linspace(0.02, 0.98, LINE_STEPS)  # where the principal point lies between two finite vanishing points
_SIGNS = np.array(np.meshgrid([1, -1], [1, -1], [1, -1])).T.reshape(-1, 3).astype(np.float64)


def _finiteness_choices(weight: np.ndarray) -> list[np.ndarray]:
    """Which vanishing points to take as finite: every choice that the doubtful ones allow."""
    sure, doubtful = weight >= DOUBTFUL, (weight > INFINITE) & (weight < DOUBTFUL)
    choices = []
    for mask in range(1 << int(doubtful.sum())):
        finite = sure.copy()
        finite[np.flatnonzero(doubtful)] = [(mask >> i) & 1 for i in range(int(doubtful.sum()))]
        choices.append(finite)
    return choices


def _plausible(theta: np.ndarray) -> np.ndarray:
    """(C,) positive extents, and for twobox the dividing plane between the outer faces."""
    if theta.shape[1] == 2:
        return (theta > 0).all(1)
    w, d, middle, h_left = theta.T
    return (w > 0) & (d > 0) & (h_left > 0) & (np.abs(middle) < w / 2)


def _to_params(theta: np.ndarray, rot: np.ndarray, t: np.ndarray, focal: float, principal: np.ndarray,
               parts: int) -> list[float]:
    """`geometry`'s vector: s = f / Tz, k = 1 / Tz, offset (Tx, Ty) in height units."""
    w, d = theta[0], theta[1]
    extra = [] if parts == 1 else [(w / 2 - theta[2]) / w, np.log(max(theta[3], 1e-6))]
    return [np.log(w), np.log(d), *rotation_vector(rot), t[0], t[1], np.log(focal / t[2]), 1.0 / t[2],
            principal[0], principal[1], *extra]
