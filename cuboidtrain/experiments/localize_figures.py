"""What `cuboidtrain localize` shows and writes: rich tables, CSV, and the paper's figures.

Figures 10 and 11 are heat maps of acc(m, l), m across, l down, each cell annotated;
Figure 12 is the softmax of negative distances over start positions for one
sub-sequence, the true start highlighted. Positions are shown 1-based.
"""
from __future__ import annotations

import csv
import textwrap
from pathlib import Path

import matplotlib
import numpy as np
from rich.table import Table

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from shared import files  # noqa: E402
from shared.files import atomic_path, json_text, save_figure  # noqa: E402

TRUE_COLOUR, OTHER_COLOUR = "#d62728", "#9aa5b1"


def accuracy_table(result: dict) -> Table:
    """acc(m, l) in percent, one row per m, one column per l."""
    settings = result["settings"]
    source = f"oracle, noise {settings['oracle_noise']:g}" if settings["oracle"] else "model"
    table = Table(title=f"acc(m, l), {settings['buildings']} buildings, {settings['streets']} street(s), {source}")
    table.add_column("m", justify="right")
    for l in result["l"]:
        table.add_column(f"top-{l}", justify="right")
    for m, row in zip(result["m"], result["acc"]):
        table.add_row(str(m), *(f"{100 * a:.0f}%" for a in row))
    return table


def ranking_table(result: dict, rows: int = 10) -> Table:
    """The practical command's answer: the most probable start positions."""
    m = len(result["masks"])
    table = Table(title=f"Where {m} photographed building(s) start in a street of "
                        f"{len(result['street']['buildings'])}")
    for name, justify in (("rank", "right"), ("start", "right"), ("buildings", "left"),
                          ("distance", "right"), ("probability", "right")):
        table.add_column(name, justify=justify)
    for row in result["ranking"][:rows]:
        table.add_row(str(row["rank"]), str(row["start"] + 1), ", ".join(row["buildings"]),
                      f"{row['distance']:.3f}", f"{100 * row['probability']:.1f}%")
    return table


def write_csv(path: str | Path, result: dict) -> None:
    """One row per m: m, then acc(m, 1) .. acc(m, L)."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["m", *(f"top_{l}" for l in result["l"])])
        for m, row in zip(result["m"], result["acc"]):
            writer.writerow([m, *(f"{a:.4f}" for a in row)])


def plot_accuracy(path: str | Path, result: dict, title: str | None = None) -> None:
    """Figures 10-11: acc(m, l) as an annotated heat map, m across, l down."""
    acc = np.asarray(result["acc"]).T  # (L, M): l down, m across
    settings = result["settings"]
    if title is None:
        source = (f"oracle ratios, relative noise {settings['oracle_noise']:g}" if settings["oracle"]
                  else "ratios of the fitted cuboid (--cuboid)" if settings.get("cuboid")
                  else "predicted ratios (R, S, T)")
        title = (f"Localization accuracy acc(m, l): {settings['buildings']} buildings, "
                 f"{settings['streets']} street(s), {source}")
    width = min(max(0.42 * acc.shape[1] + 1.8, 5.0), 15.0)
    fig, ax = plt.subplots(figsize=(width, 0.42 * acc.shape[0] + 1.6))
    image = ax.imshow(acc, cmap="viridis", vmin=0.0, vmax=1.0, aspect="auto")
    for (l, m), value in np.ndenumerate(acc):
        ax.text(m, l, f"{100 * value:.0f}", ha="center", va="center", fontsize=8,
                color="black" if value > 0.6 else "white")
    ax.set_xticks(range(acc.shape[1]), result["m"], fontsize=8)
    ax.set_yticks(range(acc.shape[0]), [f"top-{l}" for l in result["l"]], fontsize=8)
    ax.set_xlabel("m: buildings photographed in a row (sub-sequence length)")
    ax.set_ylabel("l: candidates kept")
    ax.set_title(wrapped(title, width), fontsize=10)
    fig.colorbar(image, ax=ax, fraction=0.03, pad=0.01).set_label("acc (cell labels in %)", fontsize=8)
    save_figure(fig, path, dpi=100)


def plot_start_probabilities(path: str | Path, probabilities, true_start: int | None, names: list[str],
                             title: str, label: str = "true start") -> None:
    """Figure 12: one bar per start position (its first building's name), `true_start` in red
    with `label` over it."""
    probabilities = np.asarray(probabilities)
    colours = [TRUE_COLOUR if j == true_start else OTHER_COLOUR for j in range(len(probabilities))]
    width = min(max(0.35 * len(probabilities) + 2.0, 6.0), 15.0)
    fig, ax = plt.subplots(figsize=(width, 3.4))
    ax.bar(range(len(probabilities)), probabilities, color=colours)
    step = 1 if len(probabilities) <= 30 else 5  # every label of a long street would be unreadable
    ticks = [j for j in range(len(probabilities)) if j % step == 0 or j == true_start]
    ax.set_xticks(ticks, [names[j] for j in ticks], fontsize=8)
    ax.set_xlabel("start position: first building of the sub-sequence")
    ax.set_ylabel("softmax(-distance)")
    ax.set_ylim(0, max(1e-9, probabilities.max()) * 1.15)
    if true_start is not None:
        ax.annotate(f"{label}\n{100 * probabilities[true_start]:.0f}%", (true_start, probabilities[true_start]),
                    xytext=(0, 4), textcoords="offset points", ha="center", fontsize=8, color=TRUE_COLOUR)
    ax.set_title(wrapped(title, width), fontsize=10)
    save_figure(fig, path, dpi=100)


def wrapped(title: str, width_inches: float) -> str:
    """The title in lines that fit the figure (about 11 characters an inch at 10 pt)."""
    return textwrap.fill(title, width=int(width_inches * 11))


def plot_example(path: str | Path, result: dict) -> None:
    """Figure 12 from the experiment's first street."""
    example, settings = result["example"], result["settings"]
    start, m = example["true_start"], example["m"]
    source = f"oracle, noise {settings['oracle_noise']:g}" if settings["oracle"] else "predicted ratios"
    title = (f"Where do buildings {start + 1}-{start + m} (m = {m}, {source}) start in a street of "
             f"{settings['buildings']}? softmax(-distance) per start")
    names = [str(j + 1) for j in range(len(example["probabilities"]))]
    plot_start_probabilities(path, example["probabilities"], start, names, title)


def plot_ranking(path: str | Path, result: dict) -> None:
    """Figure 12 for the practical command: no true start is known, the most probable is marked."""
    by_start = sorted(result["ranking"], key=lambda r: r["start"])
    names = [r["buildings"][0] for r in by_start]
    title = f"{len(result['masks'])} photographed building(s): probability of each start position"
    best = result["ranking"][0]["start"]
    plot_start_probabilities(path, [r["probability"] for r in by_start], best, names, title, label="most probable")


def write_json(out: str | None, result: dict) -> None:
    """`-`: stdout; a path: written atomically; None: nothing."""
    if out == "-":
        print(json_text(result, indent=2))
    elif out is not None:
        files.write_json(Path(out), result, indent=2)
