"""REPORT.md and its plots from `cuboidtrain.experiments.report`'s results.

Every number in the report comes from the ReportResults (also written beside it
as report.json, by `ReportResults.to_dict`); the paper's own figures are quoted as
constants here, with where they come from. Errors at the model's size are also given
in 256 px units (x 256 / size), the paper's resolution, so the columns compare.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from shared.files import atomic_path, save_figure, write_json  # noqa: E402

if TYPE_CHECKING:  # the experiments import torch; writing the report needs none of it
    from cuboidtrain.experiments.report import ReportResults

PAPER_TABLE3 = {  # paper, Table 3: mean px error on clean synthetic validation masks, 256 px
    "random weights": 17.9,
    "trained with rep. meaning": 0.6,
    "trained with rep. meaning, T replaced with PDM": 0.6,
    "pre-trained with rep. meaning, trained without rep. meaning": 0.8,
    "uninitialized, trained without rep. meaning": 1.0,
}
SHAPE_COLOURS = {"box": "#1f77b4", "twobox": "#d62728"}


def write_report(results: ReportResults, out: Path, command: str, localization: Path | None = None) -> list[Path]:
    """REPORT.md, report.json and the PNGs in `out`; returns the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    figures = [
        _plot(out / "noise.png", results, "noise", "contour noise std (px at 256 px)",
              "Figure 14: error against contour noise (no occlusion)", x_key="contour_noise_256px"),
        _plot(out / "occlusion.png", results, "occlusion", "occluded fraction of the silhouette",
              "Error against occlusion (no contour noise)",
              category=lambda r: f"{r['occluded_from']:.2f}-{r['occluded_to']:.2f}"),
        _plot(out / "refinement.png", results, "refinement", "Refiner passes",
              "Iterative refinement (Figure 7), noisy and occluded masks", category=lambda r: str(r["refine_steps"])),
        _extractor_plot(out / "extractors.png", results),
    ]
    write_json(out / "report.json", results.to_dict(), indent=2)
    text = markdown(results, command, localization)
    with atomic_path(out / "REPORT.md") as tmp:
        tmp.write_text(text)
    return [out / "REPORT.md", out / "report.json", *figures]


def _units(results: ReportResults, shape: str) -> float:
    return 256 / results.models[shape]["size"]


def _plot(path: Path, results: ReportResults, key: str, x_label: str, title: str, x_key: str | None = None,
          category=None) -> Path:
    """One line per shape of `key`'s rows: at `row[x_key]`, or evenly spaced and labelled by
    `category(row)` (occlusion bins, refinement passes). Rows without a value leave a gap."""
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for shape, data in results.shapes.items():
        rows = data.get(key, [])
        points = [(k if category else r[x_key], r["mean_px_error"]) for k, r in enumerate(rows)
                  if r.get("mean_px_error") is not None]
        if not points:
            continue
        ax.plot(*zip(*points), "o-", color=SHAPE_COLOURS.get(shape),
                label=f"{shape} ({results.models[shape]['size']} px model)")
        if category:
            ax.set_xticks(range(len(rows)), [category(r) for r in rows], fontsize=8)
    ax.set_xlabel(x_label)
    ax.set_ylabel("mean keypoint error (px at the model's size)")
    ax.set_title(title, fontsize=10)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, path, dpi=110)
    return path


def _extractor_plot(path: Path, results: ReportResults) -> Path:
    fig, ax = plt.subplots(figsize=(7.2, 4.0))
    groups = [(shape, spool) for shape, data in results.shapes.items() for spool in data["extractors"]]
    names = list(next(iter(results.shapes.values()))["extractors"]["clean"])
    width = 0.8 / max(len(groups), 1)
    for g, (shape, spool) in enumerate(groups):
        values = [results.shapes[shape]["extractors"][spool][n] for n in names]
        xs = [k + (g - (len(groups) - 1) / 2) * width for k in range(len(names))]
        ax.bar(xs, values, width, label=f"{shape}, {spool}", color=SHAPE_COLOURS.get(shape),
               alpha=1.0 if spool == "clean" else 0.5, edgecolor="black", linewidth=0.4)
    ax.set_xticks(range(len(names)), names)
    ax.set_ylabel("mean keypoint error (px at the model's size)")
    ax.set_title("Keypoint extractors on the same heat maps", fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, path, dpi=110)
    return path


def _fmt(value, digits: int = 2) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def markdown(results: ReportResults, command: str, localization: Path | None) -> str:
    lines = ["# cuboid-fit: report", "",
             f"Made by `{command}`. Every figure below comes from `report.json` beside this file.", ""]
    lines += _models_section(results)
    lines += _table3_section(results)
    lines += _noise_section(results)
    lines += _occlusion_section(results)
    lines += _refinement_section(results)
    lines += _extractor_section(results)
    lines += _selection_section(results)
    if localization is not None:
        lines += _localization_section(localization)
    return "\n".join(lines) + "\n"


def _models_section(results: ReportResults) -> list[str]:
    lines = ["## Models", "", "| shape | role | checkpoint | step |", "| --- | --- | --- | --- |"]
    for shape, models in results.models.items():
        for role in ("trained", "finetune", "e2e"):
            if models[role]:
                lines.append(f"| {shape} | {role} | `{models[role]['path']}` | {models[role]['step']} |")
    sizes = {m["size"] for m in results.models.values()}
    lines += ["", f"Models are {', '.join(map(str, sorted(sizes)))} px; the paper's are 256 px. Errors are in px "
              "at the model's size, and in brackets in 256 px units (x 256 / size) where they sit beside the "
              "paper's.", ""]
    return lines


def _table3_section(results: ReportResults) -> list[str]:
    shapes = list(results.shapes)
    lines = ["## Table 3: configurations on clean validation masks", "",
             "| configuration | paper (256 px) | " + " | ".join(f"{s}: mean (256 px units), median" for s in shapes) + " |",
             "| --- | --- | " + " | ".join("---" for _ in shapes) + " |"]
    for k, name in enumerate(PAPER_TABLE3):
        cells = []
        for shape in shapes:
            row = results.shapes[shape]["table3"][k]
            if "mean_px_error" not in row:
                cells.append("not trained")
            else:
                cells.append(f"{row['mean_px_error']:.2f} ({row['mean_px_error'] * _units(results, shape):.1f}), "
                             f"{row['median_px_error']:.2f}")
        lines.append(f"| {name} | {PAPER_TABLE3[name]} | " + " | ".join(cells) + " |")
    samples = {s: results.shapes[s]["table3"][0]["samples"] for s in shapes}
    lines += ["", "Samples: " + ", ".join(f"{s} {n} from `{results.shapes[s]['clean_spool']}`"
                                          for s, n in samples.items()) + ". "
              + "The PDM row projects argmax locations onto " + ", ".join(
                  f"{m['pdm']['components']} components ({s}, {m['pdm']['variance_fraction']} of the shape variance)"
                  for s, m in results.models.items()) + ", fitted on 2,000 generated keypoint sets.", ""]
    return lines


def _noise_section(results: ReportResults) -> list[str]:
    lines = ["## Figure 14: error against contour noise", "",
             "The paper's Figure 14 plots the average pixel error against the level of noise around the "
             "silhouette's contour and finds it grows with the noise despite the Refiner. Ours, with no "
             "occluders, each level on the same poses:", "", "![noise](noise.png)", "",
             "| contour noise std (px at 256 px) | " + " | ".join(f"{s} mean px" for s in results.shapes) + " |",
             "| --- | " + " | ".join("---" for _ in results.shapes) + " |"]
    levels = [r["contour_noise_256px"] for r in next(iter(results.shapes.values()))["noise"]]
    for k, level in enumerate(levels):
        lines.append(f"| {level} | " + " | ".join(_fmt(d["noise"][k]["mean_px_error"])
                                                  for d in results.shapes.values()) + " |")
    return lines + [""]


def _occlusion_section(results: ReportResults) -> list[str]:
    lines = ["## Error against occlusion", "",
             "Occluders only (no contour noise), binned by the fraction of the silhouette they hide. "
             "The paper has no such figure.", "", "![occlusion](occlusion.png)", "",
             "| occluded fraction | " + " | ".join(f"{s} mean px (samples)" for s in results.shapes) + " |",
             "| --- | " + " | ".join("---" for _ in results.shapes) + " |"]
    first = next(iter(results.shapes.values()))["occlusion"]
    for k, row in enumerate(first):
        cells = [f"{_fmt(d['occlusion'][k]['mean_px_error'])} ({d['occlusion'][k]['samples']})"
                 for d in results.shapes.values()]
        lines.append(f"| {row['occluded_from']:.2f} to {row['occluded_to']:.2f} | " + " | ".join(cells) + " |")
    return lines + [""]


def _refinement_section(results: ReportResults) -> list[str]:
    shapes = [s for s, d in results.shapes.items() if "refinement" in d]
    if not shapes:
        return []
    lines = ["## Iterative refinement", "",
             "The Refiner re-entered on its own binarised output (paper, Figure 7: each pass removes more "
             "occlusion), on the noisy and occluded validation spool. 0 passes hands the raw mask to S.", "",
             "![refinement](refinement.png)", "",
             "| Refiner passes | " + " | ".join(f"{s} mean px | {s} R IoU" for s in shapes) + " |",
             "| --- | " + " | ".join("--- | ---" for _ in shapes) + " |"]
    for k, row in enumerate(results.shapes[shapes[0]]["refinement"]):
        cells = [f"{_fmt(results.shapes[s]['refinement'][k]['mean_px_error'])} | "
                 f"{_fmt(results.shapes[s]['refinement'][k]['refiner_iou'], 3)}" for s in shapes]
        lines.append(f"| {row['refine_steps']} | " + " | ".join(cells) + " |")
    return lines + ["", "At 0 passes the IoU column compares the raw input with the clean mask.", ""]


def _extractor_section(results: ReportResults) -> list[str]:
    groups = [(s, spool) for s, d in results.shapes.items() for spool in d["extractors"]]
    names = list(next(iter(results.shapes.values()))["extractors"]["clean"])
    lines = ["## Keypoint extractors", "",
             "The same heat maps S(R(x1)) read by each extractor (`--extractor`); ratios are always T's. "
             "The paper found the PDM on argmax locations about as accurate as T on synthetic data "
             "(Table 3: 0.6 and 0.6 px).", "", "![extractors](extractors.png)", "",
             "| extractor | " + " | ".join(f"{s} {spool}" for s, spool in groups) + " |",
             "| --- | " + " | ".join("---" for _ in groups) + " |"]
    for name in names:
        lines.append(f"| {name} | " + " | ".join(_fmt(results.shapes[s]["extractors"][spool][name])
                                                for s, spool in groups) + " |")
    return lines + [""]


def _selection_section(results: ReportResults) -> list[str]:
    selection = results.shape_selection
    if not selection:
        return []
    shapes = list(selection["confusion"])
    lines = ["## Shape selection (`--shape auto`)", "",
             f"Both models on {selection['samples']} noisy, occluded samples ({selection['samples'] // len(shapes)} "
             f"of each class, seeds {selection['seeds'][0]:,} to {selection['seeds'][1]:,}, not those the 0.02 "
             f"margin was chosen on): **{selection['accuracy']:.1%} right**.", "",
             "| true \\ chosen | " + " | ".join(shapes) + " |", "| --- | " + " | ".join("---" for _ in shapes) + " |"]
    for truth in shapes:
        lines.append(f"| {truth} | " + " | ".join(str(selection["confusion"][truth][c]) for c in shapes) + " |")
    return lines + [""]


def _localization_section(path: Path) -> list[str]:
    """A pointer to the localization report (issue 5), with its headline if its JSON is there."""
    lines = ["## Localization (paper section 5)", "", f"See [{path.name}]({path.name}).", ""]
    data_path = path.with_name("localization-100-model.json")
    if data_path.is_file():
        acc = json.loads(data_path.read_text())["acc"]
        first = next((m + 1 for m, row in enumerate(acc) if row[0] >= 0.5), None)
        second = next((m + 1 for m, row in enumerate(acc) if len(row) > 1 and row[1] >= 0.5), None)
        lines += [f"100 buildings: top-1 reaches 50% at m = {first} (paper: 8); top-2 at m = {second} (paper: 3).", ""]
    return lines
