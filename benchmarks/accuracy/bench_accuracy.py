"""Accuracy as a user meets it: generated 256 px masks through `infer`, scored against the samples' keypoints.

For each validation set (a spool of 256 px samples: `paper-clean`, noisy and
occluded `paper`, `street`) and each shape class, every sample's noisy mask is
written as a PNG and fitted by `cuboidtrain.Fitter` (as `cuboidtrain infer` fits it): reading,
the building's pieces, framing, R, S, T, and the map back to the input's pixels. The
mean corner error is then in 256 px units by construction. Beside it:

* `eval`'s figures on the same spool (`cuboidtrain.train.evaluate`), px x 256 / size,
  and the error budget they carry: R's IoU, S's peak error (DARK on S's maps
  against the truth), T alone on true heat maps, and the whole chain;
* where the error is (`cuboidtrain.geometry.accuracy`): corners on the true silhouette's hull
  against the hidden interior ones, NME as a share of the building's image span, the
  depth/height and width/height relative errors of the record's ratios, the yaw error
  (degrees, modulo a half turn) and the 3D IoU of the box up to scale (Objectron's
  measure, the fit scaled about the camera so that its centre's depth is the truth's),
  against the camera each sample was drawn with (its `params`), and the focal length's
  relative error, which explains most of a low 3D IoU. The networks-only
  record has no box: its yaw and 3D IoU are those of its keypoints lifted
  (`cuboidtrain.geometry.lift.lift`); `--cuboid`'s are its fitted box's;
* shape selection (box against twobox, `--shape auto`) on the noisy sets;
* the whole `infer` path's latency per mask (median of --latency-repeats single-mask
  calls, both models, the shape chosen), with the `paper` arch at the same size as the
  baseline run in the same process.

With `--cuboid`, every figure is taken twice on the same masks, networks only and
`infer --cuboid` (`cuboidtrain.fit.cuboid`): a row per path, shape selection on every set,
and the median ms per mask of the selection run (both models, both cuboid fits).

    .venv/bin/python benchmarks/accuracy/bench_accuracy.py --samples 300 --json bench-accuracy.json

`--sets` picks the sets (`irregular`, irregular buildings, beside the default three), `--paths` the
paths, `--selection-only` scores shape selection alone, and `--tuning-seeds` draws masks of other
seeds, on which a rule may be tuned before it is measured on the usual ones.

Spools are drawn on first use under --spools (seeded, so every run scores the same masks).

The JSON (--json; also printed on one line after the tables):

* `command`, `models` (shape -> checkpoint), `threads`, `targets` (set -> mean px bound,
  `selection`, `latency_ms`);
* `rows`: networks only, one per (set, shape); `cuboid_rows` (--cuboid): the same keys for
  `infer --cuboid`. Each row: `set`, `shape`, `path`, `samples`, `size` (model px);
  `infer_mean_256` / `infer_median_256` (mean / median over masks of the per-mask mean
  corner error, 256 px units); `failed` (error records); from `where.summarise`, over the
  masks that did not fail: `hull_mean_px` / `hull_median_px` and `interior_mean_px` /
  `interior_median_px` (corners pooled), `interior_share`, `nme_mean` / `nme_median`
  (fraction of the span), `depth_height_mean_rel` / `..._median_rel` and
  `width_height_mean_rel` / `..._median_rel` (|fit / true - 1|), `posed` (masks with a
  true camera), `yaw_mean_deg` / `yaw_median_deg` ([0, 90] degrees), `iou3d_mean` /
  `iou3d_median` (in [0, 1]), `focal_mean_rel` / `focal_median_rel` (|fit / true - 1|, over
  the perspective fits); networks rows without --no-eval add `eval_mean_256`,
  `refiner_iou`, `s_peaks_dark_256`, `t_alone_256` and `skipped` (eval's);
* `selection` (networks; set -> share of masks given their true shape), `cuboid_selection`
  (--cuboid: path -> set, for `cuboid` and `cuboid_camera_given`, each mask's true camera held);
  `selection_by_shape` (path -> set -> true shape -> the share of its masks given it); `set_aside`
  (path -> set -> true shape -> `seam` / `sliver`: masks whose record set the better-explaining twobox
  aside as a box with a seam or with a sliver, `fit.cuboid.implausible`);
  `mask_ms` (path -> set -> median ms a mask of the selection run); the rows' `within_1sd` /
  `within_2sd`: how often the truth lies within the cuboid fit's error bars; `camera_inside`
  (fits with a corner at or behind the camera: it stands inside or behind the box) and
  `nearest_depth_min` (the least nearest-corner depth over the box centre's);
* `latency`: `shipped_ms`, `paper_arch_ms`, `ratio`, and `cuboid_ms` with --cuboid; empty with
  `--latency-repeats 0` (the campaign's lease evaluation: no paper arch built).
"""
from __future__ import annotations

import argparse
import json
import statistics
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from cuboidtrain.models.checkpoint import load_model
from cuboidtrain.train.evaluate import evaluate
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.infer.records import to_record, to_records
from cuboidtrain.models.networks import build_model
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.models.zoo import default_checkpoints
from cuboidtrain.geometry.accuracy import Truth, against_truth, summarise
from shared.sample import decode
from shared.spool import enumerate_spool, read_sample_bytes

SETS = ("paper-clean", "paper", "street")
NOISY_SETS = ("paper", "street", "irregular")
# Every set --sets may name: the default three and `irregular` (irregular buildings: issue 37, Must have 6).
ALL_SETS = (*SETS, "irregular")
# Seeds of the validation spools: distinct from every training spool's (recipes/shipped.sh uses 11-22).
SEEDS = {("box", "paper-clean"): 14, ("box", "paper"): 15, ("box", "street"): 16, ("box", "irregular"): 17,
         ("twobox", "paper-clean"): 24, ("twobox", "paper"): 25, ("twobox", "street"): 26, ("twobox", "irregular"): 27}
# --tuning-seeds: each set's seed plus this, masks a choice may be tuned on without seeing the measured ones.
TUNING_OFFSET = 100
TARGETS = {"paper-clean": 2.0, "paper": 3.0, "street": 3.0, "irregular": 3.0, "selection": 0.95, "latency_ms": 30.0}
PATHS = ("networks", "cuboid", "cuboid_camera_given")


def cuboidgen_command() -> list[str]:
    """`cuboidgen` beside this interpreter (a venv), else the module run by it (a lent GPU machine has
    the project on PYTHONPATH, not installed: `cuboidtrain campaign lease` evaluates there)."""
    script = Path(sys.executable).parent / "cuboidgen"
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from cuboidgen.cli import main; sys.argv[0] = 'cuboidgen'; main()"]


def spool_for(root: Path, shape: str, scene: str, samples: int, size: int = 256, seed: int | None = None) -> Path:
    """The seeded `size` px validation spool of (shape, scene) (`seed`: SEEDS' unless given; shape
    `mix` for both classes), its first `samples` samples the seeded sequence's. One that holds
    fewer is drawn afresh, not topped up: a second draw with the same seed repeats the first's
    samples (spools topped up so held 82 distinct masks in their first 200)."""
    seed = SEEDS[shape, scene] if seed is None else seed
    spool = root / (f"val-{scene}-{shape}-{size}" if (size, seed) == (256, SEEDS.get((shape, scene))) else
                    f"val-{scene}-{shape}-{size}-seed{seed}")
    if not spool.is_dir() or len(enumerate_spool(spool)) < samples:
        shutil.rmtree(spool, ignore_errors=True)
        subprocess.run([*cuboidgen_command(), "run", "--spool", str(spool), "--shape", shape,
                        "--size", str(size), "--scene", scene, "--seed", str(seed), "--limit", "0",
                        "--max-samples", str(samples), "--workers", "1", "--no-dashboard"],
                       check=True, capture_output=True)
    return spool


def write_masks(spool: Path, samples: int, folder: Path) -> tuple[list[str], list[Truth]]:
    """The first `samples` samples' noisy masks as PNGs: their paths, and their truths (keypoints,
    ratios, camera)."""
    paths, truths = [], []
    for name in enumerate_spool(spool)[:samples]:
        sample = decode(read_sample_bytes(spool, name))
        path = folder / f"{spool.name}-{len(paths):04d}.png"
        cv2.imwrite(str(path), sample.noisy.astype(np.uint8) * 255)
        paths.append(str(path))
        truths.append(Truth.of_sample(sample))
    return paths, truths


def fit_records(fitter: Fitter, files: list[str]) -> tuple[list[dict], list]:
    """`infer`'s records (`Fitter.outcomes`) and the Fits behind them, None for an error record: a
    cuboid's camera, which the 3D figures need, is in its Fit, not in the record. The Fits are
    caught through `records`' per-fit hook (`explain`), which adds no warning here."""
    fits = [None] * len(files)

    def keep(index: int, path: str, fit) -> tuple[str, ...]:
        fits[index] = fit
        return ()

    return to_records(fitter.outcomes(files, explain=keep), fitter.options), fits


def corner_errors(records: list[dict], truths: list[Truth]) -> list[float]:
    """Mean corner error per record, in the input's px (256 px units here); a failed record is NaN."""
    errors = []
    for record, truth in zip(records, truths):
        if record["error"] is not None:
            errors.append(float("nan"))
            continue
        errors.append(float(np.linalg.norm(np.asarray(record["keypoints"]) - truth.keypoints, axis=1).mean()))
    return errors


def where_figures(records: list[dict], fits: list, truths: list[Truth]) -> dict:
    """Hull / interior corner error, NME, ratio, yaw and 3D IoU errors of the records that did not
    fail: a cuboid record's 3D box is its fit's, a networks-only record's its keypoints lifted."""
    return summarise([against_truth(np.asarray(r["keypoints"]), r["ratios"], t, None if f.cuboid is None else f.cuboid.fit.camera,
                            None if f.cuboid is None else f.cuboid.fit.spread)
                      for r, f, t in zip(records, fits, truths) if r["error"] is None])


def with_cameras(options: FitOptions, variant: str, files: list[str], truths: list[Truth]) -> FitOptions:
    """The variant's options for these masks: `cuboid_camera_given` holds each mask's true camera."""
    if variant != "cuboid_camera_given":
        return options
    return replace(options, cameras=tuple((f, t.known_camera()) for f, t in zip(files, truths)))


# A record's warning that the richer class explained the input better but was set aside, by why
# (`fit.cuboid.implausible`): the plausibility gates' decisions, counted.
SET_ASIDE_REASONS = {"seam": "a box with a seam", "sliver": "a box with a sliver"}


def selected(fitter: Fitter, files: list[str], shape: str, times: list[float]) -> tuple[int, dict]:
    """How many of `files` (all of true class `shape`) `infer` gives `shape`, one call a mask (its ms appended
    to `times`: the whole infer path's), and how many records set a better-explaining class aside, by reason."""
    right, aside = 0, dict.fromkeys(SET_ASIDE_REASONS, 0)
    for file in files:
        start = time.perf_counter()
        record = to_record(fitter.outcomes([file])[0])
        times.append(1000 * (time.perf_counter() - start))
        right += record["shape"] == shape
        for reason, words in SET_ASIDE_REASONS.items():
            aside[reason] += any("was set aside" in w and words in w for w in record["warnings"])
    return right, aside


def eval_figures(model, spool: Path, samples: int) -> dict:
    """`eval` on the same spool, in 256 px units, with the error budget (S's peaks by DARK)."""
    scale = 256 / model.size
    chain = evaluate(model, spool, model.sigma, FitOptions(device="cpu"), max_samples=samples)
    peaks = evaluate(model, spool, model.sigma, FitOptions(device="cpu", extractor="dark"), max_samples=samples)
    return {"eval_mean_256": chain.mean_px_error * scale, "refiner_iou": chain.refiner_iou,
            "s_peaks_dark_256": peaks.mean_px_error * scale,
            "t_alone_256": chain.tabulator_px_error_on_true_heatmaps * scale, "skipped": chain.skipped}


def timed_latency(args, models: dict, variants: dict, folder: Path) -> dict:
    """The whole `infer` path's ms per mask, the shipped models against the paper arch's at their size
    (and with --cuboid); building the paper arch's ResNets is most of a short run's set-up."""
    example = write_masks(spool_for(args.spools, "box", "paper", 1), 1, folder)[0][0]
    size = next(iter(models.values())).size
    baseline = [build_model(s, size, arch="paper").eval() for s in models]
    latency = {"shipped_ms": latency_ms(list(models.values()), example, args.latency_repeats),
               "paper_arch_ms": latency_ms(baseline, example, args.latency_repeats)}
    if "cuboid" in variants:
        latency["cuboid_ms"] = latency_ms(list(models.values()), example, args.latency_repeats, variants["cuboid"])
    return latency | {"ratio": latency["shipped_ms"] / latency["paper_arch_ms"]}


def latency_ms(models: list, path: str, repeats: int, options: FitOptions = FitOptions(device="cpu")) -> float:
    """Median wall time of one whole `Fitter.outcomes` call (`cuboidtrain infer`) on one mask file."""
    fitter = Fitter(models, options)
    fitter.outcomes([path])  # warm-up: first-call allocations, lazy imports
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fitter.outcomes([path])
        times.append(time.perf_counter() - start)
    return 1000 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--checkpoint", nargs="*", type=Path, help="box and twobox models (default: the shipped ones)")
    parser.add_argument("--samples", type=int, default=300, help="masks per set and shape")
    parser.add_argument("--spools", type=Path, default=Path("spools"))
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--latency-repeats", type=int, default=30, help="single-mask infer calls timed; 0: none")
    parser.add_argument("--no-eval", action="store_true", help="skip eval's figures and the error budget")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--cuboid", action="store_true", help="also score `infer --cuboid` on the same masks")
    parser.add_argument("--no-selection", action="store_true",
                        help="skip shape selection (every mask again through both models): the rows only")
    parser.add_argument("--sets", nargs="+", choices=ALL_SETS, default=list(SETS), help="the sets scored")
    parser.add_argument("--paths", nargs="+", choices=PATHS, default=None,
                        help="the paths scored (default: networks, and the cuboid's two with --cuboid)")
    parser.add_argument("--selection-only", action="store_true",
                        help="shape selection only: no rows (each mask through its own class's model)")
    parser.add_argument("--tuning-seeds", action="store_true",
                        help=f"masks of other seeds (each set's plus {TUNING_OFFSET}): for tuning, not for figures")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    paths = default_checkpoints(args.checkpoint)
    models = {m.shape: m for m in (load_model(p)[0] for p in paths)}
    cuboid = FitOptions(device="cpu", cuboid=True)
    every = {"networks": FitOptions(device="cpu"), "cuboid": cuboid, "cuboid_camera_given": cuboid}
    variants = {name: every[name] for name in args.paths or (PATHS if args.cuboid else ("networks",))}
    args.cuboid = args.cuboid or any(name.startswith("cuboid") for name in variants)
    # `rows` and `selection` keep their old form (cuboidtrain models pack --validation reads them): networks only.
    rows, selection, cuboid_selection, mask_ms, by_shape, set_aside = [], {}, {}, {}, {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.sets:
            for variant, options in variants.items():
                chosen, total, times = 0, 0, []
                for shape, model in models.items():
                    seed = SEEDS[shape, scene] + TUNING_OFFSET if args.tuning_seeds else None
                    spool = spool_for(args.spools, shape, scene, args.samples, seed=seed)
                    files, truths = write_masks(spool, args.samples, Path(tmp))
                    given = with_cameras(options, variant, files, truths)
                    if not args.selection_only:
                        records, fits = fit_records(Fitter([model], replace(given, shape=shape)), files)
                        errors = corner_errors(records, truths)
                        row = {"set": scene, "shape": shape, "path": variant, "samples": len(files), "size": model.size,
                               "infer_mean_256": float(np.nanmean(errors)), "infer_median_256": float(np.nanmedian(errors)),
                               "failed": int(np.isnan(errors).sum())} | where_figures(records, fits, truths)
                        if not args.no_eval and variant == "networks":
                            row |= eval_figures(model, spool, args.samples)
                        rows.append(row)
                    if (scene in NOISY_SETS or args.cuboid) and len(models) > 1 and not args.no_selection:
                        right, aside = selected(Fitter(list(models.values()), given), files, shape, times)
                        chosen += right
                        total += len(files)
                        by_shape.setdefault(variant, {}).setdefault(scene, {})[shape] = right / len(files)
                        set_aside.setdefault(variant, {}).setdefault(scene, {})[shape] = aside
                if total:
                    (selection if variant == "networks" else cuboid_selection.setdefault(variant, {}))[scene] = chosen / total
                    mask_ms.setdefault(variant, {})[scene] = statistics.median(times)
        latency = timed_latency(args, models, variants, Path(tmp)) if args.latency_repeats else {}
    result = {"command": " ".join(sys.argv), "models": {s: str(p) for s, p in zip(models, paths)},
              "threads": args.threads, "rows": [r for r in rows if r["path"] == "networks"], "selection": selection,
              "mask_ms": mask_ms, "selection_by_shape": by_shape, "set_aside": set_aside, "latency": latency,
              "targets": TARGETS}
    if args.cuboid:
        result |= {"cuboid_rows": [r for r in rows if r["path"].startswith("cuboid")], "cuboid_selection": cuboid_selection}
    show(result)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


def show(result: dict) -> None:
    table = Table(title="Corner error in 256 px units, through infer (framing included) and eval")
    for column in ("set", "shape", "path", "samples", "infer mean", "infer median", "eval mean", "R IoU",
                   "S peaks (DARK)", "T alone", "target"):
        table.add_column(column)
    rows = sorted(result["rows"] + result.get("cuboid_rows", []), key=lambda r: (ALL_SETS.index(r["set"]), r["shape"]))
    for r in rows:
        table.add_row(r["set"], r["shape"], r["path"], str(r["samples"]), f"{r['infer_mean_256']:.2f}",
                      f"{r['infer_median_256']:.2f}",
                      *("-" if k not in r else f"{r[k]:.3f}" if k == "refiner_iou" else f"{r[k]:.2f}"
                        for k in ("eval_mean_256", "refiner_iou", "s_peaks_dark_256", "t_alone_256")),
                      f"<= {TARGETS[r['set']]}")
    console = Console()
    console.print(table)
    console.print(where_table(rows))
    selections = {"networks": result["selection"]} | result.get("cuboid_selection", {})
    for variant, by_scene in selections.items():
        for scene, accuracy in by_scene.items():
            shares = result["selection_by_shape"].get(variant, {}).get(scene, {})
            aside = result["set_aside"].get(variant, {}).get(scene, {})
            each = ", ".join(f"{shape} {100 * share:.1f}% (set aside: "
                             + ", ".join(f"{n} {why}" for why, n in aside.get(shape, {}).items()) + ")"
                             for shape, share in shares.items())
            console.print(f"{variant}: shape selection on {scene}: {100 * accuracy:.1f}% ({each}; target >= 95%), "
                          f"median {result['mask_ms'][variant][scene]:.1f} ms a mask")
    lat = result["latency"]
    if not lat:
        console.print("latency not timed (--latency-repeats 0)")
        print(json.dumps(result))
        return
    console.print(f"infer per mask ({result['threads']} thread(s), both models): {lat['shipped_ms']:.1f} ms "
                  f"(target <= 30); paper arch at the same size {lat['paper_arch_ms']:.1f} ms, ratio {lat['ratio']:.2f}"
                  + (f"; --cuboid {lat['cuboid_ms']:.1f} ms" if "cuboid_ms" in lat else ""))
    print(json.dumps(result))


def where_table(rows: list[dict]) -> Table:
    """Where the error is: hull against interior corners (mean / median), NME, ratio, yaw, 3D IoU and focal errors."""
    table = Table(title="Where the error is (256 px units; ratios: relative error; yaw: degrees modulo a half turn; "
                        "3D IoU up to scale; mean / median; networks' yaw and 3D IoU: its keypoints lifted)")
    for column in ("set", "shape", "path", "all px", "hull px", "interior px", "interior share", "NME % span",
                   "depth/height", "width/height", "yaw deg", "3D IoU", "focal", "truth in 1 / 2 sd"):
        table.add_column(column)
    for r in rows:
        table.add_row(r["set"], r["shape"], r["path"], f"{r['infer_mean_256']:.2f} / {r['infer_median_256']:.2f}",
                      f"{r['hull_mean_px']:.2f} / {r['hull_median_px']:.2f}",
                      f"{r['interior_mean_px']:.2f} / {r['interior_median_px']:.2f}", f"{100 * r['interior_share']:.0f}%",
                      f"{100 * r['nme_mean']:.2f} / {100 * r['nme_median']:.2f}",
                      f"{100 * r['depth_height_mean_rel']:.1f}% / {100 * r['depth_height_median_rel']:.1f}%",
                      f"{100 * r['width_height_mean_rel']:.1f}% / {100 * r['width_height_median_rel']:.1f}%",
                      f"{r['yaw_mean_deg']:.1f} / {r['yaw_median_deg']:.1f}",
                      f"{r['iou3d_mean']:.3f} / {r['iou3d_median']:.3f}",
                      f"{100 * r['focal_mean_rel']:.0f}% / {100 * r['focal_median_rel']:.0f}%",
                      "-" if not np.isfinite(r["within_1sd"]) else f"{100 * r['within_1sd']:.0f}% / {100 * r['within_2sd']:.0f}%")
    return table


if __name__ == "__main__":
    main()
