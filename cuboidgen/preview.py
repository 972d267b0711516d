"""A preview grid of spool samples: the noisy input beside the clean silhouette with
its keypoints, their indices and the wireframe."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from shared.errors import UsageError  # noqa: E402
from shared.files import save_figure  # noqa: E402
from shared.sample import Sample, decode  # noqa: E402
from shared.shapes import get_shape  # noqa: E402
from shared.spool import check_spool, enumerate_spool, read_sample_bytes  # noqa: E402

EDGE_COLOUR = "#2ca02c"  # the paper's green wireframe
INDEX_COLOUR = "#d62728"  # and red indices


def newest_samples(spool: Path, count: int) -> list[Sample]:
    """Up to `count` of the newest decodable samples, newest last."""
    spool = check_spool(spool)
    samples = []
    for name in reversed(enumerate_spool(spool)):
        data = read_sample_bytes(spool, name)
        if data is None:
            continue
        try:
            samples.append(decode(data))
        except ValueError:
            continue
        if len(samples) == count:
            break
    return samples[::-1]


def draw_wireframe(ax, sample: Sample, label: bool = True) -> None:
    shape = get_shape(sample.shape)
    k = sample.keypoints
    for a, b in shape.edges:
        ax.plot([k[a, 0], k[b, 0]], [k[a, 1], k[b, 1]], color=EDGE_COLOUR, lw=1.2)
    ax.scatter(k[:, 0], k[:, 1], s=10, color=INDEX_COLOUR, zorder=3)
    if label:
        for i, (x, y) in enumerate(k):
            ax.annotate(str(i), (x, y), xytext=(3, -3), textcoords="offset points", color=INDEX_COLOUR,
                        fontsize=7, fontweight="bold")


def render_grid(samples: list[Sample], out: Path, columns: int = 4) -> Path:
    """Write the grid: two panels per sample (noisy input | clean + keypoints)."""
    if not samples:
        raise UsageError("no samples to preview: the spool holds no decodable sample")
    rows = -(-len(samples) // columns)
    fig, axes = blank_grid(rows, 2 * columns, (4.2 * columns, 2.3 * rows))
    for i, sample in enumerate(samples):
        left, right = axes[i // columns, 2 * (i % columns)], axes[i // columns, 2 * (i % columns) + 1]
        extent = (-0.5, sample.size - 0.5, sample.size - 0.5, -0.5)  # pixel centres at integers
        left.imshow(sample.noisy, cmap="gray", vmin=0, vmax=1, extent=extent)
        p = sample.params
        left.set_title(f"input · occl {p.get('occluded_fraction', 0):.0%} · noise {p.get('contour_noise', 0):.1f}px",
                       fontsize=7)
        right.imshow(np.where(sample.clean, 0.85, 0.15), cmap="gray", vmin=0, vmax=1, extent=extent)
        draw_wireframe(right, sample)
        right.set_xlim(-0.5, sample.size - 0.5)
        right.set_ylim(sample.size - 0.5, -0.5)
        right.set_title(f"{sample.shape} · seed {sample.seed}", fontsize=6)
    return save_figure(fig, out, dpi=110)


def render_occluders(library, out: Path, columns: int = 10) -> Path:
    """Tile every cutout of an occluder library, labelled with its kind."""
    if not len(library):
        raise UsageError("the occluder library is empty")
    rows = -(-len(library) // columns)
    fig, axes = blank_grid(rows, columns, (1.3 * columns, 1.5 * rows))
    for ax, mask, name in zip(axes.ravel(), library.masks, library.names):
        ax.imshow(mask, cmap="gray_r", vmin=0, vmax=1)
        ax.set_title(name, fontsize=7)
    fig.suptitle(f"occluders: {library.source} ({len(library)})", fontsize=9)
    return save_figure(fig, out, dpi=100)


def blank_grid(rows: int, columns: int, figsize: tuple[float, float]):
    fig, axes = plt.subplots(rows, columns, figsize=figsize, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    return fig, axes
