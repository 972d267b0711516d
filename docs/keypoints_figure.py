"""Draw docs/keypoints.png: the keypoint convention of docs/contract.md, from real samples.

The boxes are not drawn by hand: each is a sample made by the generator itself
(`cuboidgen.synth.make_sample`, from a scene whose ranges are single values), so the
numbers and names in the picture are the ones the code gives (shared/shapes.py names,
shared/camera.py's viewer-term naming, shared/raster.py's pixel-centre rule).

    .venv/bin/python docs/keypoints_figure.py [--out docs/keypoints.png]
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from cuboidgen.config import PAPER_CLEAN  # noqa: E402
from cuboidgen.occluders import OccluderLibrary  # noqa: E402
from cuboidgen.synth import make_sample  # noqa: E402
from shared.shapes import BOX_EDGES, get_shape  # noqa: E402

SIZE = 256
# One pose for both shapes: seen from above and a little to the right, so the top, the
# front and the right side show and no two corners fall on one another.
POSE = replace(
    PAPER_CLEAN, name="figure", width=(1.7, 1.7), height=(1.0, 1.0), depth=(1.1, 1.1),
    pitch_deg=(0.0, 0.0), yaw_deg=(-25.0, -25.0), roll_deg=(0.0, 0.0),
    offset_x=(0.6, 0.6), offset_y=(1.6, 1.6), distance=(4.0, 4.0),
    flip_probability=0.0, margin=(0.2, 0.2), centre_jitter=0.0,
    split=(0.45, 0.45), height_ratio=(0.45, 0.45),
)
# Deeper for twobox: at the box's depth its hidden corners 1 and 0 fall within 12 px of 11.
TWOBOX_POSE = replace(POSE, depth=(1.5, 1.5))
FRONT_COLOUR, BACK_COLOUR = "tab:orange", "tab:blue"  # as the explanations draw the wireframe


def sample(shape: str, seed: int = 0):
    return make_sample(shape, TWOBOX_POSE if shape == "twobox" else POSE, SIZE, seed, OccluderLibrary([], [], "none"))  # clean: nothing to occlude with


def draw_shape(ax, shape_name: str, seed: int, title: str) -> None:
    s = sample(shape_name, seed)
    geometry, points = get_shape(shape_name), s.keypoints
    # extent: pixel (row i, column j) is drawn centred on (x = j, y = i), the convention itself
    ax.imshow(s.clean, cmap="Greys", vmin=0, vmax=3, extent=(-0.5, SIZE - 0.5, SIZE - 0.5, -0.5))
    front = set(geometry.having("FRONT").tolist())
    for part in geometry.parts:
        for a, b in BOX_EDGES:
            i, j = part[a], part[b]
            on_front, on_back = i in front and j in front, i not in front and j not in front
            ax.plot(*points[[i, j]].T, color=FRONT_COLOUR if on_front else BACK_COLOUR,
                    lw=2.2 if on_front else 1.2, ls="--" if on_back else "-")
    centre = points.mean(axis=0)
    for k, (x, y) in enumerate(points):
        away = np.array([x, y]) - centre
        away = away / max(np.linalg.norm(away), 1e-9)
        colour = FRONT_COLOUR if k in front else BACK_COLOUR
        ax.plot(x, y, "o", ms=5, color=colour, mec="black", mew=0.6)
        ax.text(x + away[0] * 11, y + away[1] * 11, f"{k}", fontsize=10, weight="bold", ha="center",
                va="center", bbox=dict(boxstyle="circle,pad=0.12", fc="white", ec=colour, lw=1.2))
    # the viewer terms, where they point in this picture
    lo, hi = points.min(axis=0), points.max(axis=0)
    mid = (lo + hi) / 2
    terms = dict(fontsize=8, color="0.25", ha="center", va="center", style="italic")
    ax.text(mid[0], lo[1] - 24, "TOP (up)", **terms)
    ax.text(mid[0], hi[1] + 24, "BOTTOM", **terms)
    ax.text(lo[0] - 22, mid[1], "LEFT\n(image-\nleft)", **terms)
    ax.text(hi[0] + 22, mid[1], "RIGHT", **terms)
    # low in the front face: its centre holds the hidden back corners
    tops, bottoms = (points[[k for k in sorted(front) if word in geometry.keypoint_names[k]]] for word in ("TOP", "BOTTOM"))
    face = (points[sorted(front)][:, 0].mean(), 0.3 * tops[:, 1].mean() + 0.7 * bottoms[:, 1].mean())
    ax.text(*face, "FRONT face\n(toward the camera)", fontsize=7.5, color=FRONT_COLOUR, ha="center", va="center",
            weight="bold", bbox=dict(fc="white", ec="none", alpha=0.7), zorder=1)
    names = [f"{k:2d} {n}" for k, n in enumerate(geometry.keypoint_names)]
    half = (len(names) + 1) // 2
    for column, chunk in enumerate((names[:half], names[half:])):
        ax.text(0.02 + 0.5 * column, -0.1, "\n".join(chunk), transform=ax.transAxes, fontsize=8,
                family="monospace", va="top")
    ax.set_title(title, fontsize=10)
    ax.set_xlim(-0.5, SIZE - 0.5)
    ax.set_ylim(SIZE - 0.5, -0.5)  # y down
    ax.set_xlabel("x (px) →", fontsize=8, labelpad=1)
    ax.set_ylabel("y (px) ↓", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.text(4, SIZE - 6, "FRONT face: orange; BACK face: dashed blue; FRONT-BACK edges: blue", fontsize=7, va="bottom", color="0.2")


def draw_pixel_centres(ax) -> None:
    """A zoom on the box sample's corner 7: integer coordinates are pixel centres, and a pixel
    is in the silhouette when its centre is inside the hull."""
    s = sample("box")
    x7, y7 = s.keypoints[7]
    cx, cy, r = int(round(x7)), int(round(y7)), 4
    ax.imshow(s.clean, cmap="Greys", vmin=0, vmax=3, extent=(-0.5, SIZE - 0.5, SIZE - 0.5, -0.5))
    for v in np.arange(-0.5, SIZE, 1.0):  # pixel borders at half-integers
        ax.axvline(v, color="0.75", lw=0.5)
        ax.axhline(v, color="0.75", lw=0.5)
    ys, xs = np.mgrid[cy - r:cy + r + 1, cx - r:cx + r + 1]
    inside = s.clean[ys.clip(0, SIZE - 1), xs.clip(0, SIZE - 1)]
    ax.plot(xs[inside], ys[inside], ".", color="black", ms=4, label="centre inside: pixel set")
    ax.plot(xs[~inside], ys[~inside], ".", color="0.6", ms=4, label="centre outside")
    geometry = get_shape("box")
    for a, b in BOX_EDGES:
        if 7 in (a, b):
            ax.plot(*s.keypoints[[a, b]].T, color=FRONT_COLOUR if a >= 4 and b >= 4 else BACK_COLOUR, lw=1.5)
    ax.plot(x7, y7, "o", ms=7, color=FRONT_COLOUR, mec="black")
    ax.annotate(f"7 {geometry.keypoint_names[7]}\n({x7:.2f}, {y7:.2f})", (x7, y7), (x7 - 3.8, y7 + 2.2),
                fontsize=7, bbox=dict(fc="white", ec="none", alpha=0.8))
    ax.set_xlim(cx - r - 0.5, cx + r + 0.5)
    ax.set_ylim(cy + r + 0.5, cy - r - 0.5)
    ax.set_xticks(range(cx - r, cx + r + 1))
    ax.set_yticks(range(cy - r, cy + r + 1))
    ax.tick_params(labelsize=7)
    ax.set_title("pixel centres: pixel (row i, col j) is at (x=j, y=i)", fontsize=9)
    ax.legend(fontsize=6.5, loc="lower right", framealpha=0.9)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("keypoints.png"))
    out = parser.parse_args().out
    fig, axes = plt.subplots(1, 3, figsize=(17, 8.4), gridspec_kw={"width_ratios": [1, 1, 0.7]})
    draw_shape(axes[0], "box", 0, "box: paper Table 1 (8 keypoints, 4·FRONT + 2·LEFT + BOTTOM)")
    draw_shape(axes[1], "twobox", 0, "twobox: paper Table 2 (14 keypoints; parts 0-7 and 8,3,9,10,11,7,12,13)")
    draw_pixel_centres(axes[2])
    # room below the axes for the name tables (tight_layout ignores text placed in axes units)
    fig.subplots_adjust(left=0.04, right=0.99, top=0.94, bottom=0.2, wspace=0.15)
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main()
