"""A fit that reaches the silhouette (issue 37, Must have 4): clean generated masks through `infer --cuboid`, the restart off and on.

Each class's `paper-clean` masks (seeded spools of their own, not the ones the restart was tuned
on: seeds 31 and 32) are fitted as `infer` fits them (both shipped models, the shape chosen), twice
in the same process, mask by mask: **before**, the first start alone (`mask_fit.RESTART_IOU` below
any IoU, `Fitter.reached` restarting nothing, `Fitter.settled` settling nothing), and **after**, as
shipped. Per class and size: the share of masks whose chosen cuboid's silhouette IoU is at least
0.99, the "box with a seam" warnings, the share given their own class and the corner error (px of
the mask, mean and median of the per-mask mean, over the masks given their own class).

`--oracle` measures instead how far the silhouette can be reached at all, per class and size: the
IoU of the true cuboid's own silhouette (drawn by the generator's rasteriser: 1 on a clean mask), of
the fit started from the true cuboid on the objective `infer` minimises (`mask_fit.fit_from`: the
objective's own optimum there), and of `infer`'s fit.

`--records N` times instead what the restart costs, as `bench_infer.py --records` does: the whole
record of each of N generated masks (box and twobox, three scenes), networks only, `--cuboid`
before and after, interleaved mask by mask, `--repeats` rounds; the medians' ratios.

    .venv/bin/python benchmarks/accuracy/bench_reach.py --samples 200 --size 256 --seeds 41 42
    .venv/bin/python benchmarks/accuracy/bench_reach.py --samples 200 --size 64 --seeds 43 44 --oracle
    .venv/bin/python benchmarks/accuracy/bench_reach.py --records 40 --repeats 3
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench_accuracy import cuboidgen_command
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.geometry import mask_fit
from cuboidtrain.geometry.camera_params import from_sample_params
from cuboidtrain.geometry.outline import MaskTarget
from cuboidtrain.geometry.silhouette import confidence
from shared.shapes import get_shape
from shared.sample import decode
from shared.spool import enumerate_spool, read_sample_bytes

REACHED = 0.99
SHIPPED = {"reached": Fitter.__dict__["reached"], "settled": Fitter.__dict__["settled"]}


def restarts(on: bool) -> None:
    """The restarts and the settling as shipped (`on`), or the first start alone."""
    mask_fit.RESTART_IOU = REACHED if on else -1.0
    Fitter.reached = SHIPPED["reached"] if on else (lambda self, *args: {})
    Fitter.settled = SHIPPED["settled"] if on else staticmethod(lambda *args: None)


def clean_spool(root: Path, shape: str, seed: int, samples: int, size: int) -> Path:
    """A seeded `paper-clean` spool of `samples` masks of `shape` at `size` px, drawn once."""
    spool = root / f"clean-{shape}-{seed}-{size}"
    if not spool.is_dir() or len(enumerate_spool(spool)) < samples:
        shutil.rmtree(spool, ignore_errors=True)
        subprocess.run([*cuboidgen_command(), "run", "--spool", str(spool), "--shape", shape, "--size", str(size),
                        "--scene", "paper-clean", "--seed", str(seed), "--limit", "0", "--max-samples", str(samples),
                        "--workers", "1", "--no-dashboard"], check=True, capture_output=True)
    return spool


def fitted(fitter: Fitter, sample, restart: bool) -> dict:
    """One mask's fit, the restart on or off."""
    restarts(restart)
    fit = fitter.fit(sample.clean.astype(np.uint8) * 255)
    own = fit.shape == sample.shape
    return {"iou": fit.cuboid.fit.iou, "own": own, "seam": any("a box with a seam" in w for w in fit.warnings),
            "error": float(np.linalg.norm(fit.keypoints - sample.keypoints, axis=1).mean()) if own else None}


def oracle(fitter: Fitter, sample) -> dict:
    """One clean mask's IoU of its true cuboid, of the fit from it, and of `infer`'s fit (its own class's)."""
    shape, mask = get_shape(sample.shape), sample.clean
    truth = from_sample_params(shape, sample.params)
    model = next(m for m in fitter.models if m.shape == sample.shape)
    candidate = fitter.fit_framed(model, *fitter.framed(model, mask))
    first = fitter.first_cuboid(candidate, MaskTarget.of(mask))
    return {"truth": confidence(shape, truth.keypoints(), mask),
            "from_truth": mask_fit.fit_from(first.first, 0, truth).iou,
            "infer": fitter.fit(mask.astype(np.uint8) * 255).cuboid.fit.iou}


def oracle_line(size: int, shape: str, rows: list[dict]) -> str:
    ious = {name: np.array([r[name] for r in rows]) for name in ("truth", "from_truth", "infer")}
    return (f"{size} px {shape}: true cuboid IoU least {ious['truth'].min():.4f}; IoU >= {REACHED} from the truth "
            f"{100 * np.mean(ious['from_truth'] >= REACHED):.1f}% (median {np.median(ious['from_truth']):.4f}), "
            f"infer {100 * np.mean(ious['infer'] >= REACHED):.1f}% (median {np.median(ious['infer']):.4f}); infer within "
            f"0.005 of the fit from the truth {100 * np.mean(ious['infer'] >= ious['from_truth'] - 0.005):.1f}%")


def summary(rows: list[dict]) -> dict:
    errors = np.array([r["error"] for r in rows if r["error"] is not None])
    return {"masks": len(rows), "reached": float(np.mean([r["iou"] >= REACHED for r in rows])),
            "iou_min": float(min(r["iou"] for r in rows)), "own_class": float(np.mean([r["own"] for r in rows])),
            "seam_warnings": int(sum(r["seam"] for r in rows)),
            "error_mean_px": float(errors.mean()), "error_median_px": float(np.median(errors))}


def timed(count: int, repeats: int) -> dict:
    """Median ms of the whole record, networks only and `--cuboid` before and after, interleaved."""
    sys.path.insert(0, str(Path(__file__).parents[1] / "speed"))
    from bench_infer import record_masks

    fitters = {"networks": Fitter.from_shipped(FitOptions(device="cpu")),
               "before": Fitter.from_shipped(FitOptions(device="cpu", cuboid=True)),
               "after": Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))}
    times = {name: [] for name in fitters}
    with tempfile.TemporaryDirectory() as folder:
        paths = record_masks(count, Path(folder))
        for _ in range(repeats):
            for path in paths:
                for name, fitter in fitters.items():
                    restarts(name != "before")
                    start = time.perf_counter()
                    fitter.outcomes([path])
                    times[name].append(time.perf_counter() - start)
    restarts(True)
    medians = {name: 1000 * statistics.median(t) for name, t in times.items()}
    return medians | {"before_ratio": medians["before"] / medians["networks"],
                      "after_ratio": medians["after"] / medians["networks"],
                      "mean_after_over_before": float(np.mean(times["after"]) / np.mean(times["before"]))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=int, default=200, help="masks a class")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--seeds", type=int, nargs=2, default=(41, 42), help="the box and twobox spools' seeds")
    parser.add_argument("--spools", type=Path, default=Path("spools"))
    parser.add_argument("--records", type=int, default=0, metavar="N", help="time the record instead, on N masks")
    parser.add_argument("--oracle", action="store_true", help="the true cuboid's and the fit from it's IoU instead")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.records:
        row = timed(args.records, args.repeats)
        print(f"networks {row['networks']:.1f} ms; --cuboid before {row['before']:.1f} ms ({row['before_ratio']:.3f}x), "
              f"after {row['after']:.1f} ms ({row['after_ratio']:.3f}x); mean after / before {row['mean_after_over_before']:.3f}")
        if args.json:
            args.json.write_text(json.dumps(row, indent=2) + "\n")
        return
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))
    if args.oracle:
        for shape, seed in zip(("box", "twobox"), args.seeds):
            spool = clean_spool(args.spools, shape, seed, args.samples, args.size)
            samples = [decode(read_sample_bytes(spool, name)) for name in enumerate_spool(spool)[:args.samples]]
            print(oracle_line(args.size, shape, [oracle(fitter, s) for s in samples]), flush=True)
        return
    result = {}
    for shape, seed in zip(("box", "twobox"), args.seeds):
        spool = clean_spool(args.spools, shape, seed, args.samples, args.size)
        samples = [decode(read_sample_bytes(spool, name)) for name in enumerate_spool(spool)[:args.samples]]
        for restart, label in ((False, "before"), (True, "after")):
            result[f"{shape} {label}"] = summary([fitted(fitter, s, restart) for s in samples])
    restarts(True)
    for name, row in result.items():
        print(f"{args.size} px {name}: IoU >= {REACHED} {100 * row['reached']:.1f}% (least {row['iou_min']:.3f}), "
              f"own class {100 * row['own_class']:.1f}%, seam warnings {row['seam_warnings']}, "
              f"corners {row['error_mean_px']:.2f} / {row['error_median_px']:.2f} px")
    if args.json:
        args.json.write_text(json.dumps({"size": args.size, "seeds": list(args.seeds), "rows": result}, indent=2) + "\n")


if __name__ == "__main__":
    main()
