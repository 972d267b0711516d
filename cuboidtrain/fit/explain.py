"""Explanations (paper Figure 4): how R, S and T arrived at a fit, drawn for a person.

A panel per fitted input, `<stem>.png` in the explanation folder:

    top:    the input mask with the fit in its own pixels | the framed input x1 the
            networks saw | R's refined mask with the wireframe, keypoint indices and
            the front-facing arrow | the sum of S's heat maps with the keypoints
            [| the photo with the fit, given --overlay]
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
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import matplotlib

matplotlib.use("Agg")  # files only; never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch, Rectangle  # noqa: E402

from cuboidtrain.fit.chain import no_explanation  # noqa: E402
from cuboidtrain.fit.inputs import OutputNames  # noqa: E402
from shared.errors import UsageError  # noqa: E402
from shared.files import atomic_path  # noqa: E402
from shared.raster import rasterize  # noqa: E402
from shared.shapes import Shape, get_shape  # noqa: E402

if TYPE_CHECKING:
    from cuboidtrain.fit.fitter import Fit

log = logging.getLogger(__name__)
FRONT_COLOUR, BACK_COLOUR, POINT_COLOUR = "#ff7f0e", "#17becf", "#ffdd00"
MAX_TILES_PER_ROW = 8
MIN_OVERLAY = 512  # px: a smaller photo's overlay is scaled up to at least this on its long side
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


def _input_tile(ax, mask: np.ndarray, geometry: Shape, keypoints: np.ndarray) -> None:
    """The whole input mask with the fit in input pixels, zoomed to the object and the fit."""
    _show(ax, mask, f"input mask, {mask.shape[1]} x {mask.shape[0]} px (zoomed)", cmap="gray", vmin=0, vmax=1)
    draw_fit(ax, geometry, keypoints, indices=False, arrow=False)
    ys, xs = np.nonzero(mask)
    lo = np.minimum([xs.min(), ys.min()], keypoints.min(axis=0))
    hi = np.maximum([xs.max(), ys.max()], keypoints.max(axis=0))
    pad = 0.08 * (hi - lo).max() + 2
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(hi[1] + pad, lo[1] - pad)  # images grow downwards
    mark_outside(ax, *mask.shape)


def _cuboid_residual(ax, fit: Fit) -> None:
    """With `--cuboid`: where the fitted box's silhouette and the input disagree (input minus model
    red, model minus input blue), and the networks' corners it started from (orange x), over the
    input tile, which already draws the box (its keypoints are the box's projection)."""
    mask, candidate = fit.explanation.mask, fit.explanation.candidate
    height, width = mask.shape
    model = rasterize(get_shape(fit.shape), input_keypoints(fit), max(height, width))[:height, :width]
    residual = np.zeros((height, width, 4))
    residual[mask & ~model] = (1.0, 0.15, 0.1, 0.85)  # building pixels the box leaves out: the costly miss
    residual[model & ~mask] = (0.2, 0.45, 1.0, 0.6)  # box over background: often an occluded part
    ax.imshow(residual, interpolation="nearest")
    networks = candidate.framing.to_input(np.asarray(candidate.keypoints)) if candidate.framing else None
    handles = [Patch(color=(1.0, 0.15, 0.1), label="input, not the box"),
               Patch(color=(0.2, 0.45, 1.0), label="box, not the input")]
    if networks is not None:
        ax.scatter(networks[:, 0], networks[:, 1], s=28, marker="x", color="#ff9900", linewidths=1.2, zorder=5)
        handles.append(Line2D([], [], marker="x", color="#ff9900", linestyle="", label="networks' corners"))
    ax.set_title(f"input and the fitted cuboid (IoU {fit.cuboid.fit.iou:.3f})", fontsize=9)
    ax.legend(handles=handles, loc="upper right", fontsize=7, framealpha=0.85)


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
    # Lay out in inches, then convert: a title band, the big tiles, the heat-map tiles.
    width = 16.0
    title, big, small = 0.75, width / tops * 0.92 + 0.35, width / columns * 0.92 + 0.45
    height = title + big + 0.25 + small * heat_rows
    fig = plt.figure(figsize=(width, height))
    top_edge = 1 - title / height
    top_grid = fig.add_gridspec(1, tops, top=top_edge, bottom=top_edge - big / height, left=0.01, right=0.99,
                                wspace=0.06)
    tiles = [fig.add_subplot(top_grid[0, k]) for k in range(tops)]
    _input_tile(tiles[0], fit.explanation.mask, geometry, input_keypoints(fit))
    if fit.cuboid is not None:
        _cuboid_residual(tiles[0], fit)
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
    fig.suptitle(_caption(fit), fontsize=11, y=1 - 0.12 / height)
    return fig


def input_keypoints(fit: Fit) -> np.ndarray:
    """(N, 2) float64 keypoints in the input's pixels, as the record holds them."""
    return np.asarray(fit.keypoints, dtype=np.float64)


def _caption(fit: Fit) -> str:
    ratios = fit.ratios
    if "depth_height" not in ratios:
        ratios = {f"{part}.{k}": v for part, values in ratios.items() for k, v in values.items()}
    others = ", ".join(f"{s} {c:.2f}" for s, c in fit.candidates.items() if s != fit.shape)
    name = Path(fit.input).name if fit.input is not None else "mask"  # an array fitted through the API has no file
    text = (f"{name}: {fit.shape}, confidence {fit.confidence:.2f}"
            + (f" (vs {others})" if others else "")
            + "   ratios " + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()))
    return text + ("\nwarning: " + fit.warnings[0] if fit.warnings else "")


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
    """`Fitter.records`'s explain callback: writes each fitted component's panel (and overlay) to `folder`.

    `photos[i]` is the photo behind input i (or None); a mask made at another
    resolution than its photo is scaled onto it. A picture is named after its input's file
    stem (`cuboidtrain.fit.inputs.OutputNames`; `inputs`, the run's, fix the names up front).
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
        except (OSError, ValueError, RuntimeError) as exc:  # as Fitter.records' `draw`, keeping the notes
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
