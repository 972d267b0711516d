"""Equal-time ablations: each variant trains phase 1 for the same wall-clock budget on one thread,
on the same frozen spool, side by side; then each is scored on the same validation spool with
its error budget.

Variants (--variants picks some):
  compact           the shipped arch, samples framed as infer frames them (--reframe)
  paper             the paper's three ResNet-18s, otherwise the same
  compact-noreframe the compact arch on the generator's own framing (--no-reframe), so on a
                    spool drawn at the model's size (--spool-native: the same scenes and seeds)

The error budget of each: R's IoU, S's peaks (DARK on S's maps against the truth), T alone on
true heat maps, and the whole chain, in 256 px units. Variants run concurrently (so they share
the machine's load alike); --minutes is each one's budget.

    .venv/bin/python benchmarks/accuracy/bench_ablation.py --minutes 10 --json bench-ablation.json
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import torch
from rich.console import Console
from rich.table import Table

from cuboidtrain.models.checkpoint import load_model
from cuboidtrain.train.evaluate import evaluate
from cuboidtrain.fit.options import FitOptions

VARIANTS = {
    "compact": ["--arch", "compact", "--reframe"],
    "paper": ["--arch", "paper", "--reframe"],
    "compact-noreframe": ["--arch", "compact", "--no-reframe"],
}


def train(variant: str, args) -> subprocess.Popen:
    out = args.runs / variant
    command = [str(Path(sys.executable).parent / "cuboidtrain"), "run", "--phase", "1", *VARIANTS[variant],
               "--spool", str(args.spool_native if "noreframe" in variant else args.spool), "--shape", args.shape, "--size", str(args.size), "--sigma", "2",
               "--batch-size", "32", "--lr", "1e-3", "--threads", "1", "--loader-workers", "1",
               "--max-minutes", str(args.minutes), "--checkpoint-every", "100000", "--out", str(out),
               "--no-dashboard"]
    out.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen(command, stdout=open(out / "train.log", "w"), stderr=subprocess.STDOUT)


def score(variant: str, args) -> dict:
    model, ckpt = load_model(args.runs / variant / "last.pt")
    scale = 256 / model.size
    chain = evaluate(model, args.val, model.sigma, FitOptions(device="cpu"), max_samples=args.samples)
    peaks = evaluate(model, args.val, model.sigma, FitOptions(device="cpu", extractor="dark"), max_samples=args.samples)
    return {"variant": variant, "steps": ckpt["step"], "samples_seen": ckpt["step"] * ckpt["config"]["batch_size"],
            "chain_256": chain.mean_px_error * scale, "median_256": chain.median_px_error * scale,
            "refiner_iou": chain.refiner_iou, "s_peaks_dark_256": peaks.mean_px_error * scale,
            "t_alone_256": chain.tabulator_px_error_on_true_heatmaps * scale}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--shape", default="box")
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--spool", type=Path, default=Path("spools/train-box-128"))
    parser.add_argument("--spool-native", type=Path, default=Path("spools/train-box-64"))
    parser.add_argument("--val", type=Path, default=Path("spools/val-paper-box-256"))
    parser.add_argument("--samples", type=int, default=256)
    parser.add_argument("--runs", type=Path, default=Path("runs/ablation"))
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    for process in [train(v, args) for v in args.variants]:
        if process.wait() != 0:
            raise SystemExit(f"a training run failed: see {args.runs}/*/train.log")
    rows = [score(v, args) for v in args.variants]
    table = Table(title=f"Phase 1, {args.minutes:g} min each on one thread, side by side; {args.val} "
                        f"(px at 256 px)")
    for column in ("variant", "steps", "samples", "chain", "median", "R IoU", "S peaks (DARK)", "T alone"):
        table.add_column(column)
    for r in rows:
        table.add_row(r["variant"], str(r["steps"]), f"{r['samples_seen']:,}", f"{r['chain_256']:.2f}",
                      f"{r['median_256']:.2f}", f"{r['refiner_iou']:.3f}", f"{r['s_peaks_dark_256']:.2f}",
                      f"{r['t_alone_256']:.2f}")
    Console().print(table)
    result = {"command": " ".join(sys.argv), "minutes": args.minutes, "rows": rows}
    print(json.dumps(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
