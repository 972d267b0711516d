"""The explanation panel's 3D tiles: the fitted box in its own axes, framed and seen from a side
chosen from the fit, and its camera seen from above.

The box tile draws the box rotated into its own axes (x to its RIGHT, y away from its FRONT, z
up: a rotation of the camera's frame, never a mirror), so the tile's limits are the box's and it
fills the tile; the projection is orthographic and every axis at one scale, so a box twice as wide
as deep looks it. The view is `VIEW_OFF_FACES` degrees off the two side faces nearest the camera
(nudged towards the camera's own bearing by at most `VIEW_NUDGE`) and `VIEW_ELEVATION` degrees
above: no face is seen edge-on, and the side the camera saw is in front. The corner numbers are
placed apart in the tile's 2D coordinates (`place_labels`). The camera, which would shrink the box
to a dot beside it, has a tile of its own: a plan of the camera, its view and the box's footprint.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Polygon

from cuboidtrain.infer.mesh import CameraBox, camera_box
from cuboidtrain.infer.reporting import SOURCE_WORDS, ratios_of
from shared.shapes import Shape

if TYPE_CHECKING:
    from cuboidtrain.fit.fitter import Fit

FRONT_COLOUR, BACK_COLOUR = "#ff7f0e", "#17becf"  # the panel's wireframe, 2D (explain.draw_fit) and 3D
BAND_COLOUR, GROUND_COLOUR, CAMERA_COLOUR = "#444444", "#8c8c8c", "black"
VIEW_ELEVATION = (20.0, 35.0)  # degrees above the box: its top is seen, never edge-on
VIEW_OFF_FACES = 45.0  # degrees between the view and each of the two side faces it shows
VIEW_NUDGE = 15.0  # degrees the view may turn towards the camera's bearing: 30-60 off every face
FILL = 0.86  # the share of the tile's shorter side the box's drawing spans
MAX_BAND = 2.0  # the +1 sd box is drawn at most this many times the box (a wider one would leave the tile)
MAX_DRAWN_GAP = 6.0  # box sizes: a box farther than this from its camera is drawn nearer in the plan (and said so)
LABEL_GAP = 9.0  # points between a corner and its number


@dataclass(frozen=True)
class BoxFrame:
    """A fitted box in its own axes: x to its RIGHT, y from its FRONT to its BACK (a mirrored fit's
    FRONT lies at +y: the camera's frame is turned, never mirrored), z up (units: the taller part's
    height), the origin on the ground under the middle of its footprint; and where its camera stands
    in those axes."""

    shape: Shape
    corners: np.ndarray  # (N, 3) in the record's keypoint order
    camera: np.ndarray  # (3,) the camera's centre

    @classmethod
    def of(cls, box: CameraBox) -> "BoxFrame":
        part, corners = list(box.shape.parts[0]), box.corners
        right = corners[part[0]] - corners[part[2]]  # BACK-RIGHT-TOP minus BACK-LEFT-TOP
        up = corners[part[0]] - corners[part[1]]  # BACK-RIGHT-TOP minus BACK-RIGHT-BOTTOM
        z = up / np.linalg.norm(up)
        x = right - (right @ z) * z
        x /= np.linalg.norm(x)
        rotation = np.stack([x, np.cross(z, x), z])  # rows x, y, z: det +1, a rotation
        local = corners @ rotation.T
        origin = np.array([*(local.min(axis=0)[:2] + local.max(axis=0)[:2]) / 2, local[:, 2].min()])
        return cls(box.shape, local - origin, -origin)  # the camera, at the camera frame's origin

    def bearing(self) -> tuple[float, float]:
        """The camera's azimuth and elevation seen from the box's middle, degrees (matplotlib's
        convention: azimuth from +x towards +y)."""
        middle = self.corners.mean(axis=0)
        x, y, z = self.camera - middle
        return math.degrees(math.atan2(y, x)), math.degrees(math.atan2(z, math.hypot(x, y)))


def view_angles(frame: BoxFrame) -> tuple[float, float]:
    """(elevation, azimuth) degrees: VIEW_OFF_FACES off the two side faces the camera faces most,
    turned towards the camera's bearing by at most VIEW_NUDGE, and the camera's elevation held to
    VIEW_ELEVATION's range."""
    azimuth, elevation = frame.bearing()
    quadrant = VIEW_OFF_FACES + 90.0 * math.floor((azimuth - VIEW_OFF_FACES + 45.0) / 90.0)  # the nearest diagonal
    nudge = (azimuth - quadrant + 180.0) % 360.0 - 180.0
    return (min(max(elevation, VIEW_ELEVATION[0]), VIEW_ELEVATION[1]),
            quadrant + min(max(nudge, -VIEW_NUDGE), VIEW_NUDGE))


def face_cosines(elevation: float, azimuth: float) -> np.ndarray:
    """(3,) |cos| between the view and the box's x, y and z faces' normals: each face's projected
    area over its own (an edge-on face: 0)."""
    e, a = math.radians(elevation), math.radians(azimuth)
    return np.abs([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def bands(frame: BoxFrame, fit: Fit) -> tuple[tuple[np.ndarray, np.ndarray], bool] | None:
    """The box at minus and at plus one sd of its depth and width ((N, 3) each, scaled about its middle
    by exp(-+s) along y, depth, and x, width; s the sd over the ratio, a twobox's its parts' mean, so a
    wide band stays a box), and whether s was capped at log(MAX_BAND) to stay in the tile. None
    without error bars."""
    spread = fit.cuboid.fit.spread
    if spread is None:
        return None
    relative = np.asarray(spread.ratios) / frame.shape.ratio_vector(fit.ratios)  # (d, w) per part
    depth, width = float(relative[0::2].mean()), float(relative[1::2].mean())
    cap = math.log(MAX_BAND)
    scaled = tuple(frame.corners * [math.exp(sign * min(width, cap)), math.exp(sign * min(depth, cap)), 1.0]
                   for sign in (-1.0, 1.0))
    return scaled, max(depth, width) > cap


def uncertainty_text(fit: Fit) -> str:
    """The ratios with their sd, as the answer line writes them: "d/h 0.67 ± 0.14, w/h 1.32 ± 0.26"."""
    sds = fit.cuboid.ratios_sd() if fit.cuboid is not None else None
    return ", ".join(r.text() for r in ratios_of(fit.ratios, sds))


def box3d_tile(ax, fit: Fit) -> list:
    """The fitted box in its own axes (the module's docstring), framed; its legend's handles returned."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    box = camera_box(fit.cuboid.fit)
    frame = BoxFrame.of(box)
    geometry, corners = frame.shape, frame.corners
    ax.computed_zorder = False  # drawn in layers: a translucent face sorted over an edge tinted it
    band, capped = bands(frame, fit) or ((), False)
    footprint = np.concatenate([corners, *band])
    lo, hi = footprint.min(axis=0), footprint.max(axis=0)
    pad = 0.08 * (hi - lo)[:2].max()
    ground = np.array([[lo[0] - pad, lo[1] - pad, 0], [hi[0] + pad, lo[1] - pad, 0],
                       [hi[0] + pad, hi[1] + pad, 0], [lo[0] - pad, hi[1] + pad, 0]])
    ax.add_collection3d(Poly3DCollection([ground], facecolors=GROUND_COLOUR, alpha=0.15, edgecolors=GROUND_COLOUR,
                                         linewidths=0.6, zorder=1))
    for face, cycle in (quad for _, quads in replace(box, corners=corners).faces() for quad in quads):
        front = face == "FRONT"
        ax.add_collection3d(Poly3DCollection([corners[list(cycle)]], facecolors=FRONT_COLOUR if front else BACK_COLOUR,
                                             alpha=0.4 if front else 0.12, edgecolors="none", zorder=2))
    front = set(geometry.having("FRONT").tolist())
    for a, b in geometry.edges:
        ax.plot(*corners[[a, b]].T, color=FRONT_COLOUR if a in front and b in front else BACK_COLOUR,
                linewidth=1.8, zorder=3)
    for moved in band:
        for a, b in geometry.edges:
            ax.plot(*moved[[a, b]].T, color=BAND_COLOUR, linewidth=0.8, linestyle=(0, (3, 2)), zorder=3)
    every = np.concatenate([footprint, ground])
    lo, hi = every.min(axis=0), every.max(axis=0)
    for setter, a, b in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), lo, hi):
        setter(a, b)
    ax.set_proj_type("ortho")
    elevation, azimuth = view_angles(frame)
    ax.view_init(elev=elevation, azim=azimuth)
    ax.set_axis_off()
    fill(ax, hi - lo, corners)
    place_labels(ax, corners, [str(k) for k in range(len(corners))])
    handles = [Patch(facecolor=FRONT_COLOUR, alpha=0.6, label="FRONT face"),
               Patch(facecolor=BACK_COLOUR, alpha=0.35, label="other faces"),
               Patch(facecolor=GROUND_COLOUR, alpha=0.35, label="ground"),
               Line2D([], [], marker="$k$", color="black", linestyle="", markersize=7,
                      label="corner k, as in 2D")]
    if band:
        handles.insert(2, Line2D([], [], color=BAND_COLOUR, linestyle=(0, (3, 2)), linewidth=0.8,
                                 label="-1 and +1 sd of d/h, w/h" + (f" (at most x{MAX_BAND:g})" if capped else "")))
    ax.set_title(f"the box in its own axes, seen from {elevation:.0f}° above\n{uncertainty_text(fit)}", fontsize=9)
    return handles


def fill(ax, spans: np.ndarray, corners: np.ndarray) -> None:
    """Equal scale on every axis, zoomed so the corners' drawing spans FILL of the tile's shorter side."""
    ax.set_box_aspect(spans, zoom=1.0)
    extent = projected(ax, corners)
    width, height = np.ptp(extent, axis=0)
    bbox = ax.bbox
    zoom = FILL * min(bbox.width / max(width, 1e-9), bbox.height / max(height, 1e-9))
    ax.set_box_aspect(spans, zoom=zoom)


def projected(ax, points: np.ndarray) -> np.ndarray:
    """(N, 2) display px of 3D points as the 3D axes draws them now."""
    from mpl_toolkits.mplot3d import proj3d

    ax.apply_aspect()
    x, y, _ = proj3d.proj_transform(*np.asarray(points, dtype=np.float64).T, ax.get_proj())
    return ax.transData.transform(np.column_stack([x, y]))


def place_labels(ax, points: np.ndarray, labels: list[str]) -> list:
    """Corner numbers beside their 3D points, none over another (`label_centres`), written in axes
    coordinates (2D text), so they stay where put at any dpi."""
    at = projected(ax, points)
    texts = [ax.text2D(0, 0, label, transform=ax.transAxes, fontsize=7, color="white", weight="bold", ha="center",
                       va="center", zorder=10, bbox=dict(boxstyle="round,pad=0.15", fc="black", alpha=0.6, lw=0))
             for label in labels]
    centres = label_centres(at, badge_halves(ax.figure, texts, 7), LABEL_GAP * ax.figure.dpi / 72.0)
    for text, centre in zip(texts, ax.transAxes.inverted().transform(centres)):
        text.set_position(centre)
    return texts


def badge_halves(figure, texts: list, fontsize: float, pad: float = 0.15) -> np.ndarray:
    """(N, 2) px: half of each text's width and height as drawn, with its badge's pad and a pixel to spare
    (measured once each: a layout per try cost half a second a panel)."""
    renderer = figure.canvas.get_renderer()
    sizes = np.array([[e.width, e.height] for e in (t.get_window_extent(renderer) for t in texts)])
    return sizes / 2 + pad * fontsize * figure.dpi / 72.0 + 1


def label_centres(at: np.ndarray, halves: np.ndarray, gap: float) -> np.ndarray:
    """(N, 2) px: where to centre each label of points `at` (px) so none overlaps another. The
    outermost first (they have the most room): each tried `gap` out from the points' middle, then
    turned round its point in steps and moved farther until it meets no label placed before."""
    middle = at.mean(axis=0)
    centres, placed = np.array(at, dtype=np.float64), []
    tries = [(d, t) for d in (1.0, 1.6, 2.3) for t in (0, 30, -30, 60, -60, 90, -90, 135, -135, 180)]
    for k in np.argsort(-np.linalg.norm(at - middle, axis=1), kind="stable"):
        outward = at[k] - middle
        start = math.atan2(outward[1], outward[0]) if np.linalg.norm(outward) > 1e-9 else math.pi / 4
        for distance, turn in tries:
            angle = start + math.radians(turn)
            centres[k] = at[k] + distance * gap * np.array([math.cos(angle), math.sin(angle)])
            box = (centres[k] - halves[k], centres[k] + halves[k])
            if not any(overlap(box, other) for other in placed):
                break
        placed.append(box)
    return centres


def overlap(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether two (lower left, upper right) boxes overlap."""
    return bool((a[0] < b[1]).all() and (b[0] < a[1]).all())


def camera_plan_tile(ax, fit: Fit) -> list:
    """The camera and the box seen from above (the camera's x right, z forward): the camera a black
    wedge at the origin, its view's edges dotted, the box's footprint with its FRONT edge; a box more
    than MAX_DRAWN_GAP of its sizes away is drawn nearer, in a view widened alike, and the title says
    so. Its legend's handles returned."""
    box = camera_box(fit.cuboid.fit)
    corners = box.corners
    centre = corners.mean(axis=0)
    distance, size = float(np.linalg.norm(centre)), float(np.ptp(corners, axis=0).max())
    nearer = min(1.0, MAX_DRAWN_GAP * size / distance)
    corners = corners - centre + centre * nearer
    plan = corners[:, [0, 2]]  # (x right, z forward)
    bottom = set(box.shape.having("BOTTOM").tolist())
    for part in box.shape.parts:  # each part's BOTTOM face: its footprint
        feet = plan[[i for i in part if i in bottom]]
        ax.add_patch(Polygon(feet[convex_order(feet)], closed=True, facecolor=BACK_COLOUR, alpha=0.3,
                             edgecolor=BACK_COLOUR))
    ends = plan[np.intersect1d(box.shape.having("FRONT"), box.shape.having("BOTTOM"))]
    ax.plot(*ends[np.argsort(ends[:, 0])][[0, -1]].T, color=FRONT_COLOUR, linewidth=2.5)
    height, width = fit.explanation.mask.shape
    focal = box.focal * nearer
    far = float(corners[:, 2].max()) * 1.15
    edges = (np.array([-0.5, width - 0.5]) - box.principal[0]) / focal  # x/z of the view's left and right edges
    for slope in edges:
        ax.plot([0, slope * far], [0, far], color="#777777", linewidth=0.8, linestyle=":")
    glyph = 0.06 * far
    ax.add_patch(Polygon([[0, 0], [-glyph * 0.7, -glyph], [glyph * 0.7, -glyph]], closed=True,
                         facecolor=CAMERA_COLOUR, edgecolor=CAMERA_COLOUR))
    ax.set_aspect("equal")
    every = np.concatenate([plan, [[0, -glyph]], [[slope * far, far] for slope in edges]])
    lo, hi = every.min(axis=0), every.max(axis=0)
    pad = 0.06 * (hi - lo).max()
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_xticks([])
    ax.set_yticks([])
    said = ", ".join(f"{word} {SOURCE_WORDS[fit.cuboid.source(name)]}"
                     for name, word in (("focal_px", "focal length"), ("principal_px", "centre")))
    if box.nominal:
        where = "weak perspective: no finite focal length, drawn near"
    else:
        where = f"focal {box.focal:.0f} px, {distance:.1f} box heights away" + (", drawn nearer" if nearer < 1.0 else "")
    ax.set_title(f"from above: the camera and the box\n{where}\n{said}", fontsize=9)
    return [Line2D([], [], marker="^", color=CAMERA_COLOUR, linestyle="", markersize=8, label="camera"),
            Line2D([], [], color="#777777", linestyle=":", label="its view's left and right edges"),
            Patch(facecolor=BACK_COLOUR, alpha=0.4, edgecolor=BACK_COLOUR, label="the box's footprint"),
            Line2D([], [], color=FRONT_COLOUR, linewidth=2.5, label="its FRONT face")]


def convex_order(points: np.ndarray) -> np.ndarray:
    """The indices of 2D points' convex hull, counter-clockwise (a footprint's outline)."""
    import cv2

    hull = cv2.convexHull(points.astype(np.float32), returnPoints=False)
    return hull.ravel()
