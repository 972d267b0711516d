"""Explanations (paper Figure 4): how R, S and T arrived at a fit, drawn for a person.

A panel per fitted input, `<stem>.png` in the explanation folder, titled with the line `infer`
prints for the fit (`reporting.Answer`), why its shape won where another scored higher
(`choice_reason`), and its first warning:

    top:    the input mask with the fit in its own pixels | the framed input x1 the
            networks saw | R's refined mask with the wireframe, keypoint indices and
            the front-facing arrow | the sum of S's heat maps with the keypoints
            [| the photo with the fit, given --overlay]; one legend for their marks
    with --cuboid, a row of the fitted box: the networks' corners joined to the fitted box's (the
            hidden corners ringed) | the silhouette residual, input minus box red, box minus
            input blue, with pixel counts | the box in 3D in its own axes, framed, from a side
            that shows every face, with its ratios' sd | the camera and the box from above
            (`box_view`); each with its legend
    below:  one tile per keypoint heat map, named, with the chosen point on it; a legend

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
import textwrap
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

from cuboidtrain.fit.candidates import RICHER_SHAPE_MARGIN  # noqa: E402
from cuboidtrain.fit.cuboid import CUBOID_MARGIN  # noqa: E402
from cuboidtrain.fit.fitter import no_explanation  # noqa: E402
from cuboidtrain.geometry.silhouette import model_silhouette  # noqa: E402
from cuboidtrain.infer.inputs import OutputNames  # noqa: E402
from cuboidtrain.infer.records import to_record  # noqa: E402
from cuboidtrain.infer.reporting import Answer  # noqa: E402
from cuboidtrain.infer.box_view import (BACK_COLOUR, FRONT_COLOUR, badge_halves, box3d_tile,  # noqa: E402
                                         camera_plan_tile, label_centres)
from shared.errors import UsageError  # noqa: E402
from shared.files import atomic_path  # noqa: E402
from shared.shapes import Shape, get_shape  # noqa: E402

if TYPE_CHECKING:
    from cuboidtrain.fit.fitter import Fit

log = logging.getLogger(__name__)
POINT_COLOUR = "#ffdd00"
MAX_TILES_PER_ROW = 8
MIN_OVERLAY = 512  # px: a smaller photo's overlay is scaled up to at least this on its long side
NETWORK_COLOUR = "#e7298a"  # the networks' corners, against the fitted cuboid's
MISSED_COLOUR, EXTRA_COLOUR = (1.0, 0.15, 0.1), (0.2, 0.5, 1.0)  # input minus model, model minus input
CUBOID_ROW = 6.2  # inches: the --cuboid row, titles and legends included
LEGEND_ROW = 0.4  # inches: a row of legend under the top tiles, and under the heat maps
# The title at 11 pt: about 11 characters an inch of figure (DejaVu Sans' mean advance is ~0.55 em),
# each line about 0.22 in tall.
CAPTION_CHARS_PER_INCH = 11
TITLE_LINE_INCHES = 0.22
ARROW_COLOUR, HEAT_POINT_COLOUR = "#e41a1c", "#00ff66"
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
    if indices:  # apart from each other (`label_centres`): call it once the tile's view is final
        badges = [ax.annotate(str(k), (x, y), xytext=(0, 0), textcoords="offset points", ha="center", va="center",
                              fontsize=7 * scale, color="white", weight="bold",
                              bbox=dict(boxstyle="round,pad=0.1", fc="black", alpha=0.55, lw=0))
                  for k, (x, y) in enumerate(points)]
        at = ax.transData.transform(points)
        points_px = ax.figure.dpi / 72.0
        centres = label_centres(at, badge_halves(ax.figure, badges, 7 * scale, 0.1), 6 * scale * points_px)
        for badge, offset in zip(badges, (centres - at) / points_px):
            badge.xyann = tuple(offset)
    if arrow:
        start, end = front_arrow(geometry, points)
        ax.annotate("", xy=end, xytext=start, zorder=4,
                    arrowprops=dict(arrowstyle="-|>", color=ARROW_COLOUR, lw=2.0 * scale, mutation_scale=14 * scale))


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
    outside = _zoom(ax, mask, fitted, *([networks] if networks is not None else []))  # before the numbers' places
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


def _cuboid_row(fig, grid, fit: Fit) -> None:
    """With `--cuboid`: the networks' corners against the fitted box, the silhouette residual, the
    box in 3D in its own axes, and the camera and the box from above (`box_view`)."""
    _corners_tile(fig.add_subplot(grid[0, 0]), fit)
    _residual_tile(fig.add_subplot(grid[0, 1]), fit)
    box = fig.add_subplot(grid[0, 2], projection="3d")
    _legend_below(box, box3d_tile(box, fit), False)
    plan = fig.add_subplot(grid[0, 3])
    _legend_below(plan, camera_plan_tile(plan, fit), False)


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
        ax.scatter([keypoints[k, 0]], [keypoints[k, 1]], s=40, marker="+", color=HEAT_POINT_COLOUR, linewidths=1.2)


def explanation_figure(fit: Fit, photo: np.ndarray | None = None, photo_keypoints: np.ndarray | None = None):
    """The Figure 4 panel for one fitted component (see the module's docstring)."""
    candidate, geometry = fit.explanation.candidate, get_shape(fit.shape)
    keypoints = np.asarray(candidate.keypoints)  # model px
    columns = min(MAX_TILES_PER_ROW, geometry.num_keypoints)
    heat_rows = math.ceil(geometry.num_keypoints / columns)
    tops = 5 if photo is not None else 4
    # Lay out in inches, then convert: a title band, the big tiles and their legend, [the cuboid's
    # row,] the heat-map tiles and their legend.
    width = 16.0
    heading = caption(fit, int(width * CAPTION_CHARS_PER_INCH))
    title = max(0.95, 0.3 + TITLE_LINE_INCHES * (heading.count("\n") + 1))  # a long warning wraps: room for it
    big, small = width / tops * 0.92 + 0.35, width / columns * 0.92 + 0.45
    cuboid = CUBOID_ROW if fit.cuboid is not None else 0.0  # its tiles, their titles and legends below them
    height = title + big + LEGEND_ROW + cuboid + small * heat_rows + LEGEND_ROW
    fig = plt.figure(figsize=(width, height))
    top_edge = 1 - title / height
    top_grid = fig.add_gridspec(1, tops, top=top_edge, bottom=top_edge - big / height, left=0.01, right=0.99,
                                wspace=0.06)
    tiles = [fig.add_subplot(top_grid[0, k]) for k in range(tops)]
    input_tile(tiles[0], fit.explanation.mask, geometry, input_keypoints(fit))
    fig.legend(handles=wireframe_handles(), loc="upper center", ncol=5, fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, top_edge - (big + 0.02) / height))
    if fit.cuboid is not None:
        row_top = top_edge - (big + LEGEND_ROW + 0.5) / height  # under the top row's legend, room for the titles
        grid = fig.add_gridspec(1, 4, top=row_top, bottom=row_top - (cuboid - 1.5) / height, left=0.01, right=0.99,
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
    heat_grid = fig.add_gridspec(heat_rows, columns, top=(small * heat_rows + LEGEND_ROW) / height,
                                 bottom=(LEGEND_ROW + 0.05) / height, left=0.01, right=0.99, hspace=0.35, wspace=0.06)
    _heatmap_tiles(fig, heat_grid, geometry, candidate.heatmaps, keypoints, candidate.refined)
    fig.legend(handles=heatmap_handles(), loc="lower center", ncol=2, fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 0.02 / height))
    fig.suptitle(heading, fontsize=11, y=1 - 0.1 / height, va="top")
    return fig


def wireframe_handles() -> list:
    """The legend of the top row's marks: the wireframe, its corners and numbers, the front arrow."""
    return [Line2D([], [], color=FRONT_COLOUR, linewidth=1.6, label="fit, FRONT edges"),
            Line2D([], [], color=BACK_COLOUR, linewidth=1.6, label="fit, other edges"),
            Line2D([], [], marker="o", color=POINT_COLOUR, markeredgecolor="black", linestyle="", label="corner"),
            Line2D([], [], marker="$k$", color="black", linestyle="", markersize=7,
                   label="corner k (docs/contract.md's order)"),
            Line2D([], [], color=ARROW_COLOUR, linewidth=2.0, marker=">", markersize=6,
                   label="front-facing direction (from the FRONT face, away from the BACK)")]


def heatmap_handles() -> list:
    """The legend of the heat-map tiles' marks."""
    return [Line2D([], [], marker="+", color=HEAT_POINT_COLOUR, linestyle="", markersize=9, markeredgewidth=1.2,
                   label="the corner read from this map"),
            Line2D([], [], color="#bbbbbb", linewidth=0.8, label="the refined mask's outline")]


def input_keypoints(fit: Fit) -> np.ndarray:
    """(N, 2) float64 keypoints in the input's pixels, as the record holds them."""
    return np.asarray(fit.keypoints, dtype=np.float64)


def caption(fit: Fit, columns: int | None = None) -> str:
    """The panel's title: the line `infer` prints for the fit, why its shape won where another scored
    higher, and its first warning in full; each wrapped to `columns` characters (None: unwrapped), so
    that a twobox's line and a long warning stay inside the figure."""
    record = to_record(fit, fit.component is not None, fit.cuboid is not None)
    lines = [Answer.of(record).line(), choice_reason(fit)]
    if fit.warnings:
        lines.append("warning: " + fit.warnings[0])
    kept = [line for line in lines if line]
    if columns is not None:
        kept = [part for line in kept for part in textwrap.wrap(line, columns)]
    return "\n".join(kept)


def choice_reason(fit: Fit) -> str | None:
    """Why the chosen shape won though another class scored higher, in the words of the rule that
    chose (fit/candidates.py `choose`, fit/cuboid.py `choose_cuboid`): a richer class must score more
    than the margin higher, and a fit set aside says why in its warning; or, on a rough mask, that the
    shape classifier called it (`fit.shape_call`), always. None where the chosen one scored highest, or alone."""
    score = "IoU" if fit.cuboid is not None else "confidence"
    margin = CUBOID_MARGIN if fit.cuboid is not None else RICHER_SHAPE_MARGIN
    chosen = fit.candidates.get(fit.shape, fit.confidence)
    higher = {s: c for s, c in fit.candidates.items() if s != fit.shape and c > chosen}
    call = fit.shape_call
    if call is not None and call.shape == fit.shape:  # a rough mask: the classifier's call stood
        sure = max(call.twobox_probability, 1 - call.twobox_probability)
        digits = max(3, distinct_digits(chosen, list(higher.values())))
        return f"{fit.shape}: the shape classifier's call on this rough silhouette ({100 * sure:.0f}% sure)" + \
            "".join(f"; {s}'s {score} {c:.{digits}f} is higher than the {fit.shape}'s {chosen:.{digits}f}"
                    for s, c in higher.items())
    if not higher:
        return None
    rival, value = max(higher.items(), key=lambda item: item[1])
    digits = max(3, distinct_digits(chosen, [value]))  # 0.906 against 0.903: the margin's own digits
    said = f"{rival}'s {score} {value:.{digits}f}"
    aside = next((w for w in fit.warnings if w.startswith(f"the {rival} cuboid") and "set aside: " in w), None)
    if aside is not None:
        return f"{fit.shape}: {said} is higher, but the {rival} was set aside: {aside.split('set aside: ', 1)[1]}"
    if get_shape(rival).num_keypoints > get_shape(fit.shape).num_keypoints:
        return (f"{fit.shape}: {said} is not {margin:g} above the {fit.shape}'s {chosen:.{digits}f}, "
                f"the margin a richer shape must win by")
    return f"{fit.shape}: {said} is higher, but the {rival} was set aside (see the warnings)"


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
