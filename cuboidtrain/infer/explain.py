"""Explanations (paper Figure 4): how R, S and T arrived at a fit, drawn for a person.

A panel per fitted input, `<stem>.png` in the explanation folder:

    top:    the input mask with the fit in its own pixels | the framed input x1 the
            networks saw | R's refined mask with the wireframe, keypoint indices and
            the front-facing arrow | the sum of S's heat maps with the keypoints
            [| the photo with the fit, given --overlay]
    with --cuboid, a row of the fitted box: the networks' corners joined to the fitted box's (the
            hidden corners ringed) | the silhouette residual, input minus box red, box minus
            input blue, with pixel counts | the box in 3D beside its camera, seen obliquely from
            above, behind and to the right of the camera, at equal scale, upright (the camera's y
            is down: drawn as (x, z, -y)), FRONT face orange and corners numbered as the 2D tiles'
    below:  one tile per keypoint heat map, named, with the chosen point on it

and, given a photo, `<stem>-overlay.png`: the fit drawn over the photo at its own
resolution, or a whole multiple of it up to at least MIN_OVERLAY px on the long side
(a 70 x 49 px crop would be a postage stamp). Where a tile shows more than its image
(a keypoint outside the input), the area outside is hatched grey, named in a legend:
white is the foreground's colour. Images are shown with imshow's default extent, which puts pixel
(row i, column j) at (x = j, y = i): docs/contract.md's pixel-centre convention, so
keypoints are plotted as they are, with no half-pixel shift.
"""
from __future__ import annotations

import logging
import math
from dataclasses import replace
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import matplotlib

matplotlib.use("Agg")  # files only; never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch, Rectangle  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from cuboidtrain.fit.fitter import no_explanation  # noqa: E402
from cuboidtrain.geometry.silhouette import model_silhouette  # noqa: E402
from cuboidtrain.infer.inputs import OutputNames  # noqa: E402
from cuboidtrain.infer.mesh import camera_box, depth_band  # noqa: E402
from shared.errors import UsageError  # noqa: E402
from shared.files import atomic_path  # noqa: E402
from shared.shapes import Shape, get_shape  # noqa: E402

if TYPE_CHECKING:
    from cuboidtrain.fit.fitter import Fit

log = logging.getLogger(__name__)
FRONT_COLOUR, BACK_COLOUR, POINT_COLOUR = "#ff7f0e", "#17becf", "#ffdd00"
MAX_TILES_PER_ROW = 8
MIN_OVERLAY = 512  # px: a smaller photo's overlay is scaled up to at least this on its long side
NETWORK_COLOUR = "#e7298a"  # the networks' corners, against the fitted cuboid's
MISSED_COLOUR, EXTRA_COLOUR = (1.0, 0.15, 0.1), (0.2, 0.5, 1.0)  # input minus model, model minus input
CUBOID_ROW = 5.9  # inches: the --cuboid row, titles and legends included
DISPLAY = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # camera (x, y down, z) -> (x, z, up)
VIEW_ELEVATION, VIEW_AZIMUTH = 24.0, -50.0  # degrees: above, behind and right of the camera
CAMERA_DEPTH = 0.2  # the camera pyramid's depth, a share of the box's distance
MAX_DRAWN_GAP = 6.0  # box sizes: a box farther than this from its camera is drawn nearer (and said so)
OUTSIDE = dict(facecolor="#8c8c8c", edgecolor="#5e5e5e", hatch="///", linewidth=0)  # beyond the image


def front_arrow(geometry: Shape, keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(start, end) px of the front-facing arrow: from the front face's centre, pointing away
    from the back face (the building's facing direction, as the image shows it)."""
    front = keypoints[geometry.having("FRONT")].mean(axis=0)
    back = keypoints[geometry.having("BACK")].mean(axis=0)
    direction = front - back
    span = np.ptp(keypoints, axis=0).max()
    norm = np.linalg.norm(direction)
    # A building seen head-on has its faces' centres almost on top of each other: point down the view.
    unit = direction / norm if norm > 1e-6 * max(span, 1.0) else np.array([0.0, 1.0])
    return front, front + unit * 0.25 * max(span, 1.0)


def draw_fit(ax, geometry: Shape, keypoints: np.ndarray, scale: float = 1.0, indices: bool = True,
             arrow: bool = True) -> None:
    """The wireframe (front edges orange, the rest cyan), keypoint indices and the front arrow.
    `scale` grows lines and labels for large images."""
    points = np.asarray(keypoints, dtype=np.float64)
    front = set(geometry.having("FRONT").tolist())
    for a, b in geometry.edges:
        colour = FRONT_COLOUR if a in front and b in front else BACK_COLOUR
        ax.plot(points[[a, b], 0], points[[a, b], 1], color=colour, linewidth=1.6 * scale, alpha=0.9)
    ax.scatter(points[:, 0], points[:, 1], s=14 * scale**2, color=POINT_COLOUR, edgecolors="black",
               linewidths=0.5 * scale, zorder=3)
    if indices:
        for k, (x, y) in enumerate(points):
            ax.annotate(str(k), (x, y), xytext=(3 * scale, -3 * scale), textcoords="offset points",
                        fontsize=7 * scale, color="white", weight="bold",
                        bbox=dict(boxstyle="round,pad=0.1", fc="black", alpha=0.55, lw=0))
    if arrow:
        start, end = front_arrow(geometry, points)
        ax.annotate("", xy=end, xytext=start, zorder=4,
                    arrowprops=dict(arrowstyle="-|>", color="#e41a1c", lw=2.0 * scale, mutation_scale=14 * scale))


def _show(ax, image, title: str, **kwargs) -> None:
    ax.imshow(image, interpolation="nearest", **kwargs)
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])


def mark_outside(ax, height: int, width: int) -> bool:
    """Hatch the part of the tile's view beyond its `height` x `width` image and name it in a
    legend; True when there is such a part. Call it once the view's limits are final."""
    (x0, x1), (y1, y0) = ax.get_xlim(), ax.get_ylim()  # y grows downwards
    if x0 >= -0.5 and y0 >= -0.5 and x1 <= width - 0.5 and y1 <= height - 0.5:
        return False
    ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, zorder=-1, **OUTSIDE))
    for image in ax.get_images():
        image.set_zorder(0)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)
    ax.legend(handles=[Patch(label="outside the input", **OUTSIDE)], loc="lower right", fontsize=7, framealpha=0.85)
    return True


def _zoom(ax, mask: np.ndarray, *points: np.ndarray) -> bool:
    """Zoom `ax` to the mask's object and `points` (input px), hatching what lies beyond the image
    (`mark_outside`); True when there is such a part."""
    ys, xs = np.nonzero(mask)
    every = np.concatenate([np.stack([xs, ys], axis=1).astype(np.float64), *points])
    lo, hi = every.min(axis=0), every.max(axis=0)
    pad = 0.08 * (hi - lo).max() + 2
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(hi[1] + pad, lo[1] - pad)  # images grow downwards
    return mark_outside(ax, *mask.shape)


def input_tile(ax, mask: np.ndarray, geometry: Shape, keypoints: np.ndarray) -> None:
    """The whole input mask with the fit in input pixels, zoomed to the object and the fit."""
    _show(ax, mask, f"input mask, {mask.shape[1]} x {mask.shape[0]} px (zoomed), with the fit", cmap="gray",
          vmin=0, vmax=1)
    draw_fit(ax, geometry, keypoints, indices=False, arrow=False)
    _zoom(ax, mask, keypoints)


def _legend_below(ax, handles: list, outside: bool) -> None:
    """A legend under the tile, clear of the image (a legend inside hid a corner), with the hatched
    'outside the input' entry when the tile has such a part."""
    if outside:
        handles = handles + [Patch(label="outside the input", **OUTSIDE)]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.01), ncol=2, fontsize=7.5,
              framealpha=0.9, handlelength=1.6, columnspacing=1.0, borderaxespad=0.2)


def networks_corners(fit: Fit) -> np.ndarray | None:
    """(N, 2) input px: the networks' corners the cuboid fit started from, in the fitted corners'
    order (the fit's corner i is the network's corner `naming()[i]`); None without a framing."""
    candidate = fit.explanation.candidate
    if candidate.framing is None:
        return None
    corners = candidate.framing.to_input(np.asarray(candidate.keypoints))
    return corners[fit.cuboid.fit.camera.naming()]


def _corners_tile(ax, fit: Fit) -> None:
    """With `--cuboid`: the fitted box (its wireframe and corner indices) over the input, dimmed,
    and the networks' corners it started from, each joined to the fitted corner of the same name;
    the corners the outline does not fix (hidden) are ringed."""
    mask, geometry = fit.explanation.mask, get_shape(fit.shape)
    fitted = input_keypoints(fit)
    networks = networks_corners(fit)
    _show(ax, mask, "", cmap="gray", vmin=0, vmax=2.2)  # the building in grey: the lines stand out
    hidden = ~np.asarray(fit.cuboid.fit.on_outline, dtype=bool)
    ax.scatter(fitted[hidden, 0], fitted[hidden, 1], s=150, facecolors="none", edgecolors="white",
               linewidths=1.2, linestyle=(0, (2, 1.5)), zorder=2)
    draw_fit(ax, geometry, fitted, arrow=False)
    handles = [Line2D([], [], color=FRONT_COLOUR, label="cuboid, FRONT edges"),
               Line2D([], [], color=BACK_COLOUR, label="cuboid, other edges"),
               Line2D([], [], marker="o", markerfacecolor="none", markeredgecolor="black", linestyle="",
                      markersize=9, label="hidden corner (not on the outline)")]
    title = "fitted cuboid"
    if networks is not None:
        for (x0, y0), (x1, y1) in zip(networks, fitted):
            ax.plot([x0, x1], [y0, y1], color=NETWORK_COLOUR, linewidth=1.0, linestyle=(0, (3, 2)), zorder=4)
        ax.scatter(networks[:, 0], networks[:, 1], s=44, marker="x", color=NETWORK_COLOUR, linewidths=1.8, zorder=5)
        handles.append(Line2D([], [], marker="x", color=NETWORK_COLOUR, linestyle=(0, (3, 2)), markersize=7,
                              markeredgewidth=1.8, label="networks' corner -> fitted"))
        moved = np.linalg.norm(fitted - networks, axis=1)
        title = (f"networks' corners -> the fitted cuboid\nmoved {moved.mean():.1f} px mean, "
                 f"{moved.max():.1f} px most (corner {int(moved.argmax())})")
    ax.set_title(title, fontsize=9)
    outside = _zoom(ax, mask, fitted, *([networks] if networks is not None else []))
    _legend_below(ax, handles, outside)


def _residual_tile(ax, fit: Fit) -> None:
    """With `--cuboid`: where the fitted box's silhouette and the input disagree, at the input's
    pixels: input minus model red (building the box leaves out: the costly miss), model minus
    input blue (box over background: often an occluded part), both grey."""
    mask, geometry = fit.explanation.mask, get_shape(fit.shape)
    height, width = mask.shape
    fitted = input_keypoints(fit)
    model = model_silhouette(geometry, fitted, (height, width))
    residual = np.zeros((height, width, 3))
    residual[mask & model] = 0.55
    residual[mask & ~model] = MISSED_COLOUR
    residual[model & ~mask] = EXTRA_COLOUR
    _show(ax, residual, f"silhouette residual, IoU {fit.cuboid.fit.iou:.3f}")
    for a, b in geometry.edges:  # the box's outline for orientation, thin
        ax.plot(fitted[[a, b], 0], fitted[[a, b], 1], color="white", linewidth=0.6, alpha=0.5)
    handles = [Patch(color=MISSED_COLOUR, label=f"input, not the box: {int((mask & ~model).sum())} px"),
               Patch(color=EXTRA_COLOUR, label=f"box, not the input: {int((model & ~mask).sum())} px"),
               Patch(color=(0.55, 0.55, 0.55), label=f"both: {int((mask & model).sum())} px")]
    _legend_below(ax, handles, _zoom(ax, mask, fitted))


def _box3d_tile(ax, fit: Fit) -> None:
    """With `--cuboid`: the fitted box in 3D with its camera, seen from above, behind and to the
    right of the camera, at equal scale on every axis (units: box heights).

    The camera's frame (x right, y down, z forward) is drawn with up as up: display (x, z, -y),
    a rotation, so nothing is mirrored. The camera is a pyramid at the origin whose base is the
    input image's outline through the fitted focal length and principal point, a triangle on its
    top edge; its view's edges run on, dotted, to the box's far side. A box more than
    MAX_DRAWN_GAP of its sizes away (a weak-perspective fit's is NOMINAL_DISTANCE heights away) is
    drawn nearer, in a wider view, and the title says so. Faces and edges are coloured
    as the 2D tiles' (FRONT orange), the corners numbered as theirs."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    box = camera_box(fit.cuboid.fit)
    geometry, corners = box.shape, box.corners
    centre = corners.mean(axis=0)
    distance, size = float(np.linalg.norm(centre)), float(np.ptp(corners, axis=0).max())
    squeezed = distance > MAX_DRAWN_GAP * size
    nearer = MAX_DRAWN_GAP * size / distance if squeezed else 1.0
    # A far box would be a dot: it is drawn nearer, along its line of sight, and said so, before a
    # camera of a wider view (focal length times the same factor), in which it fills the image as it did.
    corners = corners - centre + centre * nearer
    show = corners @ DISPLAY.T
    # Drawn in layers (faces, then lines, then labels), not sorted by depth: a translucent face
    # sorted in front of an edge tinted the FRONT face's orange edges cyan.
    ax.computed_zorder = False
    # the box: translucent faces, FRONT orange; edges as draw_fit's; numbered corners
    for _, quads in box.faces():
        for face, cycle in quads:
            front = face == "FRONT"
            ax.add_collection3d(Poly3DCollection(
                [show[list(cycle)]], facecolors=FRONT_COLOUR if front else BACK_COLOUR,
                alpha=0.4 if front else 0.10, edgecolors="none", zorder=2))
    front = set(geometry.having("FRONT").tolist())
    for a, b in geometry.edges:
        colour = FRONT_COLOUR if a in front and b in front else BACK_COLOUR
        ax.plot(*show[[a, b]].T, color=colour, linewidth=1.8, zorder=3)
    depth_sd = _depth_bounds(ax, fit, box, corners)
    for k, point in enumerate(show):
        ax.text(*point, f" {k}", fontsize=7, color="white", weight="bold", zorder=10,
                bbox=dict(boxstyle="round,pad=0.1", fc="black", alpha=0.55, lw=0))
    below = show[np.intersect1d(geometry.having("FRONT"), geometry.having("BOTTOM"))].mean(axis=0)
    ax.text(*(below - [0.0, 0.0, 0.1 * size]), "FRONT", fontsize=8, color="#b35900", weight="bold", ha="center",
            va="top")  # under the FRONT face's bottom edge, clear of the corner numbers
    # the camera: a pyramid on the image's outline, a triangle marking the image's top
    height, width = fit.explanation.mask.shape
    (cx, cy), f = box.principal, box.focal * nearer
    # deep enough that a narrow view's pyramid is not a needle: its base at least 1/8 of the box's size
    drawn = float(np.linalg.norm(corners.mean(axis=0)))
    depth = min(max(CAMERA_DEPTH * drawn, size / 8 * f / max(height, width)), 0.4 * drawn)
    image = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    rays = np.column_stack([(image - [cx, cy]) / f, np.ones(4)])  # camera frame, z = 1
    base = rays * depth
    apex = np.zeros(3)
    ax.add_collection3d(Poly3DCollection([base @ DISPLAY.T], facecolors="#555555", alpha=0.25, edgecolors="black",
                                         linewidths=1.0, zorder=2))
    for corner in base:
        ax.plot(*(np.stack([apex, corner]) @ DISPLAY.T).T, color="black", linewidth=1.0, zorder=3)
    top = (base[0] + base[1]) / 2
    up = np.array([0.0, -1.0, 0.0]) * 0.35 * np.linalg.norm(base[1] - base[0])
    ax.add_collection3d(Poly3DCollection([np.stack([base[0] * 0.75 + base[1] * 0.25, top + up,
                                                     base[0] * 0.25 + base[1] * 0.75]) @ DISPLAY.T],
                                         facecolors="black", alpha=0.8, zorder=3))
    far = corners[:, 2].max()
    for ray in rays:  # the view's edges, on to the box's far side
        ax.plot(*(np.stack([ray * depth, ray * far]) @ DISPLAY.T).T, color="#777777", linewidth=0.7, linestyle=":")
    ax.text(*apex @ DISPLAY.T, "camera ", fontsize=8, ha="right", va="top")
    # the ground: the plane of the box's BOTTOM face, under the box and the camera, and the camera's height over it
    ground, foot = _ground(geometry, corners)
    ax.add_collection3d(Poly3DCollection([ground @ DISPLAY.T], facecolors="#8c8c8c", alpha=0.18, edgecolors="#8c8c8c",
                                         linewidths=0.6, zorder=1))
    ax.plot(*(np.stack([apex, foot]) @ DISPLAY.T).T, color="black", linewidth=0.8, linestyle=(0, (1, 2)))
    # equal scale on every axis
    every = np.concatenate([show, (base @ DISPLAY.T), apex[None], (rays * far) @ DISPLAY.T, ground @ DISPLAY.T])
    lo, hi = every.min(axis=0), every.max(axis=0)
    pad = 0.04 * (hi - lo).max()
    lo, hi = lo - pad, hi + pad
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(hi - lo, zoom=1.35)
    ax.set_proj_type("ortho")
    ax.view_init(elev=VIEW_ELEVATION, azim=VIEW_AZIMUTH)
    for axis, label in zip((ax.xaxis, ax.yaxis, ax.zaxis), ("x, right", "z, forward", "up (-y)")):
        axis.set_major_locator(MaxNLocator(4))
        axis.set_label_text(label, fontsize=7)
        axis.labelpad = -6
    ax.tick_params(labelsize=6, pad=-2)
    if box.nominal:
        where = "weak perspective (no finite focal length): the box drawn near a camera that is really infinitely far"
    elif squeezed:
        where = f"focal {box.focal:.0f} px; the box drawn nearer, in a wider view: it is {distance:.1f} box heights away"
    else:
        where = f"focal {f:.0f} px; the box {distance:.1f} box heights away"
    given = fit.cuboid.given
    said = ", ".join(f"{name.split('_')[0]} {'given' if name in given else 'fitted'}" for name in ("focal_px", "principal_px"))
    spread = "" if depth_sd is None else f"; depth x/ {math.exp(depth_sd):.2f} (1 sd) dashed"
    ax.set_title(f"the fitted box in 3D and its camera (oblique view): {said}\n{where}; units: box height{spread}",
                 fontsize=9)


def _depth_bounds(ax, fit: Fit, box, corners: np.ndarray) -> float | None:
    """The box at plus and minus one sd of its depth, dashed (`mesh.depth_band`, of the box as drawn:
    `corners`); s, the sd of log depth, returned, None without error bars."""
    band = depth_band(replace(box, corners=corners), fit.ratios, fit.cuboid.fit.spread)
    if band is None:
        return None
    relative, *bounds = band
    for moved in bounds:
        moved = moved @ DISPLAY.T
        for a, b in box.shape.edges:
            ax.plot(*moved[[a, b]].T, color="#444444", linewidth=0.8, linestyle=(0, (3, 2)), zorder=3)
    return relative


def _ground(geometry: Shape, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(4, 3) a rectangle of the plane of the (first) part's BOTTOM face, around that face and the
    camera's foot on it, and (3,) the foot: camera-frame points."""
    bottom = corners[[i for i in geometry.parts[0] if i in set(geometry.having("BOTTOM").tolist())]]
    origin = bottom.mean(axis=0)
    u = bottom[1] - bottom[0] if np.linalg.norm(bottom[1] - bottom[0]) > 1e-9 else bottom[2] - bottom[0]
    u /= np.linalg.norm(u)
    normal = np.cross(u, bottom[-1] - bottom[0])
    normal /= np.linalg.norm(normal)
    v = np.cross(normal, u)
    foot = (origin @ normal) * normal  # the camera (the origin) dropped onto the plane
    every = np.concatenate([corners, foot[None]]) - origin
    (u0, v0), (u1, v1) = (every @ np.stack([u, v]).T).min(axis=0), (every @ np.stack([u, v]).T).max(axis=0)
    pad = 0.15 * max(u1 - u0, v1 - v0)
    u0, u1, v0, v1 = u0 - pad, u1 + pad, v0 - pad, v1 + pad
    return np.array([origin + a * u + b * v for a, b in ((u0, v0), (u1, v0), (u1, v1), (u0, v1))]), foot


def _cuboid_row(fig, grid, fit: Fit) -> None:
    """With `--cuboid`: the networks' corners against the fitted box, the silhouette residual,
    and the box in 3D with its camera (two tiles wide)."""
    _corners_tile(fig.add_subplot(grid[0, 0]), fit)
    _residual_tile(fig.add_subplot(grid[0, 1]), fit)
    _box3d_tile(fig.add_subplot(grid[0, 2:], projection="3d"), fit)


def _heatmap_tiles(fig, grid, geometry: Shape, heatmaps: np.ndarray, keypoints: np.ndarray,
                   refined: np.ndarray) -> None:
    """One tile per keypoint's map, each scaled to its own peak (a faint map is still a shape one
    can read; the peak value is in the title), over the refined mask's outline for orientation."""
    columns = min(MAX_TILES_PER_ROW, geometry.num_keypoints)
    for k, (name, heatmap) in enumerate(zip(geometry.keypoint_names, heatmaps)):
        ax = fig.add_subplot(grid[k // columns, k % columns])
        _show(ax, heatmap, f"{k} {name}\npeak {heatmap.max():.2f}", cmap="magma", vmin=0, vmax=max(heatmap.max(), 1e-6))
        ax.title.set_fontsize(7)
        ax.contour(refined > 0, levels=[0.5], colors="white", linewidths=0.6, alpha=0.45)
        ax.scatter([keypoints[k, 0]], [keypoints[k, 1]], s=40, marker="+", color="#00ff66", linewidths=1.2)


def explanation_figure(fit: Fit, photo: np.ndarray | None = None, photo_keypoints: np.ndarray | None = None):
    """The Figure 4 panel for one fitted component (see the module's docstring)."""
    candidate, geometry = fit.explanation.candidate, get_shape(fit.shape)
    keypoints = np.asarray(candidate.keypoints)  # model px
    columns = min(MAX_TILES_PER_ROW, geometry.num_keypoints)
    heat_rows = math.ceil(geometry.num_keypoints / columns)
    tops = 5 if photo is not None else 4
    # Lay out in inches, then convert: a title band, the big tiles, [the cuboid's row,] the heat-map tiles.
    width = 16.0
    title, big, small = 0.75, width / tops * 0.92 + 0.35, width / columns * 0.92 + 0.45
    cuboid = CUBOID_ROW if fit.cuboid is not None else 0.0  # its tiles, their titles and legends below them
    height = title + big + 0.25 + cuboid + small * heat_rows
    fig = plt.figure(figsize=(width, height))
    top_edge = 1 - title / height
    top_grid = fig.add_gridspec(1, tops, top=top_edge, bottom=top_edge - big / height, left=0.01, right=0.99,
                                wspace=0.06)
    tiles = [fig.add_subplot(top_grid[0, k]) for k in range(tops)]
    input_tile(tiles[0], fit.explanation.mask, geometry, input_keypoints(fit))
    if fit.cuboid is not None:
        row_top = top_edge - (big + 0.25 + 0.5) / height  # under the top row, room for the titles
        grid = fig.add_gridspec(1, 4, top=row_top, bottom=row_top - (cuboid - 1.2) / height, left=0.01, right=0.99,
                                wspace=0.08)
        _cuboid_row(fig, grid, fit)
    size = candidate.refined.shape[0]
    _show(tiles[1], candidate.framed, f"framed input x1 ({size} x {size} px)", cmap="gray", vmin=0, vmax=1)
    _show(tiles[2], candidate.refined > 0, f"refined R(x1), {candidate.refine_steps} pass(es), with the fit",
          cmap="gray", vmin=0, vmax=1)
    draw_fit(tiles[2], geometry, keypoints)
    _show(tiles[3], candidate.heatmaps.sum(axis=0), "sum of heat maps S(R(x1)), with the keypoints", cmap="magma")
    draw_fit(tiles[3], geometry, keypoints, arrow=False)
    if photo is not None:
        _show(tiles[4], photo, "photo with the fit")
        draw_fit(tiles[4], geometry, photo_keypoints, indices=False, scale=max(1.0, photo.shape[1] / 800))
        mark_outside(tiles[4], *photo.shape[:2])
    heat_grid = fig.add_gridspec(heat_rows, columns, top=(small * heat_rows) / height, bottom=0.01,
                                 left=0.01, right=0.99, hspace=0.35, wspace=0.06)
    _heatmap_tiles(fig, heat_grid, geometry, candidate.heatmaps, keypoints, candidate.refined)
    fig.suptitle(caption(fit), fontsize=11, y=1 - 0.12 / height)
    return fig


def input_keypoints(fit: Fit) -> np.ndarray:
    """(N, 2) float64 keypoints in the input's pixels, as the record holds them."""
    return np.asarray(fit.keypoints, dtype=np.float64)


def caption(fit: Fit) -> str:
    """The panel's title: the input, the chosen shape and its confidence beside the others', the ratios."""
    ratios = fit.ratios
    if "depth_height" not in ratios:
        ratios = {f"{part}.{k}": v for part, values in ratios.items() for k, v in values.items()}
    rivals = {s: c for s, c in fit.candidates.items() if s != fit.shape}
    digits = distinct_digits(fit.confidence, rivals.values())
    others = ", ".join(f"{s} {c:.{digits}f}" for s, c in rivals.items())
    name = Path(fit.input).name if fit.input is not None else "mask"  # an array fitted through the API has no file
    text = (f"{name}: {fit.shape}, confidence {fit.confidence:.{digits}f}"
            + (f" (vs {others})" if others else "")
            + "   ratios " + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()))
    return text + ("\nwarning: " + fit.warnings[0] if fit.warnings else "")


def distinct_digits(value: float, others: Iterable[float], most: int = 4) -> int:
    """Decimals, 2 to `most`, at which `value` reads apart from each of `others` (0.903 against 0.901,
    not 0.90 against 0.90, which made a choice look arbitrary); `most` where they are that close."""
    others = list(others)
    return next((d for d in range(2, most) if all(f"{value:.{d}f}" != f"{o:.{d}f}" for o in others)), most)


def to_photo(points: np.ndarray, mask_shape: tuple[int, int], photo_shape: tuple[int, int]) -> np.ndarray:
    """Mask px -> photo px when the mask was made at another resolution of the same view
    (pixel centres: a pixel's centre j covers [j - 0.5, j + 0.5], so scale about -0.5)."""
    sy, sx = photo_shape[0] / mask_shape[0], photo_shape[1] / mask_shape[1]
    return (np.asarray(points, dtype=np.float64) + 0.5) * [sx, sy] - 0.5


def read_photo(path: Path) -> np.ndarray:
    """An RGB photo, or a one-line ValueError."""
    data = np.fromfile(str(path), dtype=np.uint8) if Path(path).is_file() else np.zeros(0, np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if image is None:
        raise UsageError(f"--overlay {path}: cannot read it as an image (expected a PNG or JPG photo)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def overlay_zoom(height: int, width: int) -> int:
    """Figure pixels per photo pixel: 1, or the least whole number that brings the long side to MIN_OVERLAY."""
    return max(1, math.ceil(MIN_OVERLAY / max(height, width)))


def overlay_figure(photo: np.ndarray, fit: Fit, keypoints: np.ndarray):
    """The fit over the photo: `overlay_zoom` figure pixels per photo pixel (one, from MIN_OVERLAY px up)."""
    height, width = photo.shape[:2]
    zoom, dpi = overlay_zoom(height, width), 100
    fig = plt.figure(figsize=(width * zoom / dpi, height * zoom / dpi), dpi=dpi)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(photo, interpolation="nearest")
    ax.set_axis_off()
    scale = max(1.0, width * zoom / 640)
    draw_fit(ax, get_shape(fit.shape), keypoints, scale=scale)
    ax.text(0.01 * width, 0.02 * height, f"{fit.shape} {fit.confidence:.2f}", color="white",
            fontsize=10 * scale, va="top", bbox=dict(fc="black", alpha=0.6, lw=0))
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    return fig, dpi


class Explainer:
    """`Fitter.outcomes`'s explain callback: writes each fitted component's panel (and overlay) to `folder`.

    `photos[i]` is the photo behind input i (or None); a mask made at another
    resolution than its photo is scaled onto it. A picture is named after its input's file
    stem (`cuboidtrain.infer.inputs.OutputNames`; `inputs`, the run's, fix the names up front).
    """

    def __init__(self, folder: Path, photos: list[Path] | None = None, inputs: Sequence[str] | None = None):
        self.folder, self.photos = Path(folder), list(photos or [])
        missing = [str(p) for p in self.photos if p is not None and not Path(p).is_file()]
        if missing:
            raise UsageError(f"--overlay {missing[0]}: no such file")
        if self.folder.exists() and not self.folder.is_dir():
            raise UsageError(f"--explain {self.folder}: not a folder")
        self.folder.mkdir(parents=True, exist_ok=True)
        self.written: list[Path] = []
        self.names = OutputNames(inputs)  # the run's inputs fix each picture's name (as --mesh's files')

    def __call__(self, index: int, path: str, fit: Fit) -> tuple[str, ...]:
        """Draw `fit` (input `index`, file `path`); the warnings for its record: a photo that cannot
        be read, a picture that cannot be written."""
        stem = self.names(index, path) + (f"-{fit.component}" if fit.component is not None else "")
        photo, notes = self._photo(index)
        shown = replace(fit, warnings=fit.warnings + notes)  # the caption names the first warning
        try:
            on_photo = None
            if photo is not None:
                on_photo = to_photo(input_keypoints(fit), fit.explanation.mask.shape, photo.shape[:2])
                fig, dpi = overlay_figure(photo, shown, on_photo)
                self._save(fig, self.folder / f"{stem}-overlay.png", dpi=dpi)
            self._save(explanation_figure(shown, photo, on_photo), self.folder / f"{stem}.png", dpi=110)
        except (OSError, ValueError, RuntimeError) as exc:  # as Fitter.outcomes' `draw`, keeping the notes
            warning = no_explanation(exc)
            log.warning("%s: %s", path, warning)
            return notes + (warning,)
        return notes

    def _photo(self, index: int) -> tuple[np.ndarray | None, tuple[str, ...]]:
        """Input `index`'s photo (or None), and the warning when it cannot be decoded: a warning in
        its record, not a failure."""
        if index >= len(self.photos) or self.photos[index] is None:
            return None, ()
        try:
            return read_photo(self.photos[index]), ()
        except ValueError as error:
            warning = f"no overlay: {error}"
            log.warning("%s", warning)
            return None, (warning,)

    def _save(self, fig, path: Path, dpi: int) -> None:
        try:
            with atomic_path(path) as tmp:  # a reader never sees half a picture
                fig.savefig(tmp, dpi=dpi, format="png")
        finally:
            plt.close(fig)
        self.written.append(path)
