"""Which model the GPU campaign should train (issue 40, Must have 3): candidates compared at an equal
number of samples on the CPU, and their GPU cost projected from the H100 figures.

Each candidate (an arch at a size, e.g. `compact:64`, the shipped models' today) trains phase 1
from scratch in this process on one thread, per shape, on the same frozen spool in the same order
(the trainer's seed), for the same number of samples; its checkpoint is scored at fixed shares of
them (a learning curve: 0, N/4, N/2, N by default) on the same held-out masks:
`benchmarks/accuracy/bench_accuracy.py`'s seeded 256 px validation sets, each model framing them
at its own size, so every error is in 256 px units. Per point and set: the corner error (mean and
median), on the true silhouette's outline (hull) and in its interior, the ratios' error; with
both shapes trained, shape accuracy (box against twobox through `infer`'s selection, networks only,
on the noisy `paper` masks). Per candidate: the error gained per 1,000 samples (from random
weights to N, and over the last half alone), the CPU training rate, the projected H100 rate and
samples per 8-minute lease (`GPU_RATES`, BENCHMARKS.md), and the CPU latency through `infer`
against the shipped models and the first candidate, interleaved in this process (networks only, and
the whole record with the cuboid fit, infer's default; both shapes' models, random weights: the
networks' arithmetic is the same, the fit's work after them is not).
`--rate-only` candidates (the paper's arch at 256 px: a sample takes seconds on one core) are
timed for a few steps and through `infer`, not trained to N.

Each trainer's ledger (`--ledger`) names the samples it trained on; `samples_digest` hashes them in
order, so equal digests prove the candidates saw the same samples.

    nice -n 15 .venv/bin/python benchmarks/gpu/choose_campaign_model.py --samples 4800 --json choose.json
"""
from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.infer.records import to_records
from cuboidtrain.models.checkpoint import load_model
from cuboidtrain.models.codec import default_sigma
from cuboidtrain.models.networks import ARCHS, build_model
from cuboidtrain.models.zoo import shipped_path
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.train.evaluate import evaluate
from cuboidtrain.train.ledger import read_ledger
from cuboidtrain.train.loop import run as train
from shared.errors import UsageError
from shared.spool import enumerate_spool

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "accuracy"))
sys.path.insert(0, str(HERE.parent / "speed"))
from bench_accuracy import cuboidgen_command, eval_figures, spool_for, write_masks  # noqa: E402
from bench_infer import interleaved_ms  # noqa: E402

SHAPES = ("box", "twobox")
# Heat-map std in px by size: the shipped models' 2 px at 64, the campaign plan's 3 at 128.
SIGMA = {64: 2.0, 128: 3.0}
LEASE_MINUTES = 8.0  # of a lease's 15 spent training (issue 40's target)
# Samples a second a trainer took on one H100 beside four generators (BENCHMARKS.md, "On one H100
# beside the generator"): compact 64 and 128 px alone, 1,884-2,192; slim 128 two side by side,
# 1,953-2,190 each; paper 256 batch 64 alone, 468. (arch, size) -> (low, high).
GPU_RATES = {("compact", 64): (1884, 2192), ("compact", 128): (1884, 2192), ("slim", 128): (1953, 2190),
             ("paper", 256): (468, 468)}


@dataclass(frozen=True)
class Candidate:
    """An architecture at an input size, with the heat maps' std it trains to draw."""

    arch: str
    size: int
    sigma: float

    @property
    def name(self) -> str:
        return f"{self.arch}:{self.size}"

    @classmethod
    def parse(cls, text: str) -> "Candidate":
        """`ARCH:SIZE` or `ARCH:SIZE:SIGMA`."""
        parts = text.split(":")
        if parts[0] not in ARCHS:
            raise UsageError(f"candidate {text!r}: expected ARCH:SIZE[:SIGMA], ARCH one of {', '.join(ARCHS)}")
        try:
            arch, size = parts[0], int(parts[1])
            sigma = float(parts[2]) if len(parts) > 2 else SIGMA.get(size, default_sigma(size))
        except (IndexError, ValueError):
            raise UsageError(f"candidate {text!r}: expected ARCH:SIZE or ARCH:SIZE:SIGMA, e.g. slim:128") from None
        if len(parts) > 3 or size < 32 or size % 32 or sigma <= 0:
            raise UsageError(f"candidate {text!r}: expected ARCH:SIZE[:SIGMA], the size a multiple of 32 px, "
                             f"the sigma positive")
        return cls(arch, size, sigma)


@dataclass(frozen=True)
class Point:
    """A candidate's model after `samples` training samples, as scored."""

    samples: int
    sets: dict  # set -> figures (256 px units)
    error: float  # mean corner error over the sets' masks, 256 px units


def curve_points(samples: int, batch: int, shares: int) -> list[int]:
    """Steps at which the model is scored: `shares` equal shares of the run (0 is scored apart)."""
    steps = max(1, samples // batch)
    points = sorted({max(1, round(steps * k / shares)) for k in range(1, shares + 1)})
    return points


def draw_spool(root: Path, shape: str, samples: int, seed: int) -> Path:
    """A frozen 256 px `paper` training spool of `samples` samples (seeded; drawn once, kept; one
    cut short, by a kill, drawn afresh)."""
    spool = root / f"train-{shape}-256-s{seed}-n{samples}"
    if not spool.is_dir() or len(enumerate_spool(spool)) < samples:
        shutil.rmtree(spool, ignore_errors=True)
        subprocess.run([*cuboidgen_command(), "run", "--spool", str(spool), "--shape", shape, "--size", "256",
                        "--scene", "paper", "--seed", str(seed), "--limit", "0", "--max-samples", str(samples),
                        "--workers", "1", "--no-dashboard"], check=True, capture_output=True)
    return spool


def score(model, val: dict[str, Path], masks: int) -> dict:
    """Networks-only figures of `model` on each validation set, in 256 px units."""
    figures = {}
    for name, spool in val.items():
        result = evaluate(model, spool, model.sigma, FitOptions(device="cpu"), max_samples=masks, paths=True)
        net = result.paths["networks"]
        figures[name] = {"masks": result.samples, "mean_256": net["mean_px"], "median_256": net["median_px"],
                         "outline_mean_256": net["hull_mean_px"], "interior_mean_256": net["interior_mean_px"],
                         "ratio_error": result.mean_ratio_error}
    return figures


def point_of(samples: int, figures: dict) -> Point:
    weights = [f["masks"] for f in figures.values()]
    error = float(np.average([f["mean_256"] for f in figures.values()], weights=weights))
    return Point(samples, figures, error)


def ledger_digest(folder: Path) -> tuple[int, str]:
    """Samples trained on (the ledger's names, in order) and their SHA-256: the same for runs that
    saw the same samples in the same order."""
    digest, count = hashlib.sha256(), 0
    for line in sorted(read_ledger(folder / "ledger.jsonl"), key=lambda line: line["step"]):
        for name, *_ in line["samples"]:
            digest.update(name.encode() + b"\n")
            count += 1
    return count, digest.hexdigest()[:16]


def train_candidate(c: Candidate, shape: str, spool: Path, args, val: dict[str, Path], out: Path) -> dict:
    """Phase 1 from scratch to the run's last point, scored at each; its curve, rate and digest."""
    # A run cut short before leaves its folder: the trainer's --overwrite replaces its checkpoint and
    # metrics but appends to its ledger, whose stale steps would then count as samples of this run.
    shutil.rmtree(out / "run", ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    steps = curve_points(args.samples, args.batch, args.shares)
    random_model = build_model(shape, c.size, seed=args.seed, sigma=c.sigma, arch=c.arch).eval()
    points = [point_of(0, score(random_model, val, args.masks))]
    trained_s, checkpoints = 0.0, {}
    for i, stop in enumerate(steps):
        config = TrainConfig(phase="1", spool=str(spool), shape=shape, size=c.size, arch=c.arch, sigma=c.sigma,
                             steps=steps[-1], stop_at=stop, batch_size=args.batch, lr=args.lr, seed=args.seed,
                             out=str(out / "run"), resume=i > 0, overwrite=i == 0, ledger=True, threads=1,
                             loader_workers=0, device="cpu", dashboard=False, checkpoint_every=10 ** 6,
                             max_minutes=args.max_minutes)
        start = time.perf_counter()
        status = train(config.validate())
        trained_s += time.perf_counter() - start
        if status.step != stop:
            raise SystemExit(f"{c.name} {shape}: stopped at step {status.step}, not {stop} "
                             f"(--max-minutes {args.max_minutes} ran out?)")
        model, _ = load_model(out / "run" / "last.pt")
        checkpoints[stop] = out / f"step-{stop}.pt"
        shutil.copyfile(out / "run" / "last.pt", checkpoints[stop])
        points.append(point_of(stop * args.batch, score(model, val, args.masks)))
    samples, digest = ledger_digest(out / "run")
    return {"curve": [p.__dict__ for p in points], "samples": samples, "samples_digest": digest,
            "cpu_samples_per_s": samples / trained_s, "checkpoints": {s: str(p) for s, p in checkpoints.items()},
            "gain_per_1k": gain(points[0], points[-1]), "late_gain_per_1k": gain(points[len(points) // 2], points[-1])}


def gain(before: Point, after: Point) -> float:
    """Corner error (256 px units) taken off per 1,000 samples between two points."""
    return 1000 * (before.error - after.error) / max(after.samples - before.samples, 1)


def shape_accuracy(checkpoints: dict[str, str], masks: dict[str, list[str]]) -> float:
    """Share of the masks given their true shape by infer's selection (networks only, both models)."""
    fitter = Fitter([load_model(p)[0] for p in checkpoints.values()], FitOptions(device="cpu"))
    right = total = 0
    for shape, files in masks.items():
        records = to_records(fitter.outcomes(files), fitter.options)
        right += sum(r["shape"] == shape for r in records)
        total += len(records)
    return right / total


def rate_only(c: Candidate, shape: str, spool: Path, args, out: Path) -> float:
    """CPU samples/s of a candidate too slow to train to N: the median step time of a few steps."""
    config = TrainConfig(phase="1", spool=str(spool), shape=shape, size=c.size, arch=c.arch, sigma=c.sigma,
                         steps=args.rate_steps, batch_size=args.rate_batch, lr=args.lr, seed=args.seed,
                         out=str(out), overwrite=True, threads=1, loader_workers=0, device="cpu",
                         dashboard=False, checkpoint_every=10 ** 6, log_every=1, max_minutes=args.max_minutes)
    train(config.validate())
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines() if line.strip()]
    rates = [r["samples_per_s"] for r in records if r.get("samples_per_s")]
    return float(np.median(rates[1:] or rates))  # the first step's rate holds the start-up


def latencies(candidates: list[Candidate], files: list[str], rounds: int) -> dict:
    """Median ms of one `infer` call on one mask, both shapes' models, networks only and the whole
    record (cuboid fit), each candidate against the shipped models, interleaved mask by mask.
    `ratio` is over the shipped models', `over_first` over the first candidate's: with random weights
    alike, the fairer ratio (random networks change what the fit does after them: on 2026-11-28 compact
    64 with random weights took 1.24x the shipped compact 64 networks-only, 1.18x the record)."""
    shipped = [load_model(shipped_path(s))[0] for s in SHAPES]
    fitters = {"shipped": shipped} | {c.name: [build_model(s, c.size, sigma=c.sigma, arch=c.arch).eval() for s in SHAPES]
                                      for c in candidates}
    result = {}
    for path, options in (("networks", FitOptions(device="cpu")), ("record", FitOptions(device="cpu", cuboid=True))):
        calls = {name: (lambda f=Fitter(models, options): [f.outcomes([file]) for file in files])
                 for name, models in fitters.items()}
        ms = interleaved_ms(calls, rounds, warmup=1)
        result[path] = {name: value / len(files) for name, value in ms.items()}
    first = candidates[0].name if candidates else "shipped"
    return {path: {name: {"ms": value, "ratio": value / by["shipped"], "over_first": value / by[first]}
                   for name, value in by.items()} for path, by in result.items()}


def projection(c: Candidate) -> dict | None:
    """The H100 samples/s measured for this (arch, size), and samples per 8-minute lease; None if unmeasured."""
    if (c.arch, c.size) not in GPU_RATES:
        return None
    low, high = GPU_RATES[c.arch, c.size]
    return {"h100_samples_per_s": [low, high], "samples_per_lease": [round(low * 60 * LEASE_MINUTES),
                                                                      round(high * 60 * LEASE_MINUTES)]}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--candidates", nargs="+", default=["compact:64", "slim:128", "compact:128"],
                        help="ARCH:SIZE[:SIGMA] trained to --samples (default sigma: 2 px at 64, 3 at 128)")
    parser.add_argument("--rate-only", nargs="*", default=["paper:256"], help="timed, not trained to --samples")
    parser.add_argument("--shapes", nargs="+", default=list(SHAPES), choices=SHAPES)
    parser.add_argument("--samples", type=int, default=4800, help="training samples a candidate and shape")
    parser.add_argument("--shares", type=int, default=4, help="scored after each of this many shares of --samples")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0, help="the trainers' seed: the same order of samples for all")
    parser.add_argument("--spool-seed", type=int, default=51, help="the training spools' (distinct from the sets')")
    parser.add_argument("--sets", nargs="+", default=["paper-clean", "paper"], help="bench_accuracy.py's sets")
    parser.add_argument("--masks", type=int, default=100, help="held-out masks a set and shape")
    parser.add_argument("--spools", type=Path, default=Path("spools"), help="where spools are drawn and kept")
    parser.add_argument("--runs", type=Path, default=None, help="run folders (default: a temporary one)")
    parser.add_argument("--rate-steps", type=int, default=4)
    parser.add_argument("--latency-masks", type=int, default=5)
    parser.add_argument("--latency-rounds", type=int, default=4)
    parser.add_argument("--max-minutes", type=float, default=30.0, help="guard on each training chunk")
    parser.add_argument("--cached-only", action="store_true",
                        help="train nothing: report the runs --runs already holds, time and project them")
    parser.add_argument("--rate-batch", type=int, default=8, help="batch of the --rate-only candidates' steps")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    candidates = [Candidate.parse(text) for text in args.candidates]
    slow = [Candidate.parse(text) for text in args.rate_only]
    with tempfile.TemporaryDirectory() as tmp:
        runs = args.runs or Path(tmp) / "runs"
        result = compare(candidates, slow, args, runs, Path(tmp))
    show(result)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return result


def compare(candidates: list[Candidate], slow: list[Candidate], args, runs: Path, tmp: Path) -> dict:
    """Every measurement of the module docstring, as one JSON-ready dict."""
    cache = Cache(runs / CACHE, settings(args))
    spools, val, masks = {}, {}, {}
    for shape in args.shapes:
        spools[shape] = draw_spool(args.spools, shape, args.samples, args.spool_seed + SHAPES.index(shape))
        val[shape] = {name: spool_for(args.spools, shape, name, args.masks) for name in args.sets}
        masks[shape] = write_masks(val[shape].get("paper", next(iter(val[shape].values()))), args.masks, tmp)[0]
    for c in candidates:  # a candidate's both shapes before the next candidate: a run cut short has whole ones
        for shape in args.shapes:
            if cache.has(c.name, shape) or args.cached_only:
                continue
            run = train_candidate(c, shape, spools[shape], args, val[shape], runs / c.name.replace(":", "-") / shape)
            cache.keep(c.name, shape, run)
            print(f"{c.name} {shape}: {run['curve'][-1]['error']:.2f} px after {run['samples']} samples", flush=True)
    rows = [candidate_row(c, cache.trained.get(c.name, {}), args, val, masks) for c in candidates]
    for c in slow:
        rows.append({"candidate": c.name, "arch": c.arch, "size": c.size, "sigma": c.sigma, "rate_only": True,
                     "cpu_samples_per_s": rate_only(c, args.shapes[0], spools[args.shapes[0]], args,
                                                    runs / c.name.replace(":", "-") / "rate"),
                     "gpu": projection(c)})
    files = write_masks(spool_for(args.spools, "box", "paper", args.latency_masks), args.latency_masks, tmp)[0]
    return {"command": " ".join(sys.argv), "samples": args.samples, "batch": args.batch, "sets": args.sets,
            "masks": args.masks, "lease_minutes": LEASE_MINUTES, "rows": rows,
            "latency": latencies(candidates + slow, files, args.latency_rounds)}


def candidate_row(c: Candidate, runs: dict, args, val: dict[str, dict], masks: dict[str, list[str]]) -> dict:
    """A trained candidate's figures: its runs by shape (those done) with the last model's error
    budget, and with both shapes done its shape accuracy from the curve's middle on."""
    row = {"candidate": c.name, "arch": c.arch, "size": c.size, "sigma": c.sigma,
           "shapes": {shape: runs[shape] | {"budget": budget(runs[shape], val[shape], args.masks)}
                      for shape in args.shapes if shape in runs}, "gpu": projection(c)}
    if set(row["shapes"]) == set(SHAPES):
        points = [int(step) for step in row["shapes"][SHAPES[0]]["checkpoints"]]
        row["shape_accuracy"] = {step * args.batch: shape_accuracy(
            {s: runs[s]["checkpoints"][str(step)] for s in SHAPES}, masks) for step in points[(len(points) - 1) // 2:]}
    return row


def budget(run: dict, val: dict[str, Path], masks: int) -> dict:
    """Where the last model's error is, on the noisy `paper` set (else the first): R's IoU, S's peaks
    read sub-pixel (DARK) and T alone on true heat maps, 256 px units (bench_accuracy's error budget)."""
    last = run["checkpoints"][max(run["checkpoints"], key=int)]
    return eval_figures(load_model(last)[0], val.get("paper", next(iter(val.values()))), masks)


CACHE = "trained.json"  # in --runs: each candidate's finished runs, so a later call goes on where one stopped


def settings(args) -> dict:
    """What a cached run must have been trained and scored with to be reused."""
    return {key: getattr(args, key) for key in ("samples", "shares", "batch", "lr", "seed", "spool_seed", "sets", "masks")}


class Cache:
    """The runs done, by candidate and shape, in --runs/trained.json (JSON keys: steps as strings)."""

    def __init__(self, path: Path, wanted: dict):
        self.path, self.wanted = path, wanted
        kept = json.loads(path.read_text()) if path.is_file() else {}
        self.trained = kept.get("trained", {}) if kept.get("settings") == wanted else {}

    def has(self, name: str, shape: str) -> bool:
        return shape in self.trained.get(name, {})

    def keep(self, name: str, shape: str, run: dict) -> None:
        self.trained.setdefault(name, {})[shape] = json.loads(json.dumps(run))  # as read back: string keys
        self.path.write_text(json.dumps({"settings": self.wanted, "trained": self.trained}, indent=2) + "\n")


def show(result: dict) -> None:
    """One line per candidate and shape: the curve's errors, the gains, rates, projection and latency."""
    lat = result["latency"]
    print(f"{result['samples']} samples a candidate and shape (batch {result['batch']}), phase 1 from scratch; "
          f"mean corner error in 256 px units over {result['masks']} masks of each of {', '.join(result['sets'])}")
    for row in result["rows"]:
        name = row["candidate"]
        gpu = row["gpu"]
        tail = (f"H100 {gpu['h100_samples_per_s'][0]:,}-{gpu['h100_samples_per_s'][1]:,}/s, "
                f"{gpu['samples_per_lease'][0]:,}-{gpu['samples_per_lease'][1]:,} a lease" if gpu else "H100: not measured")
        tail += "; " + "; ".join(f"infer {path} {lat[path][name]['ms']:.1f} ms ({lat[path][name]['ratio']:.2f}x shipped, "
                                 f"{lat[path][name]['over_first']:.2f}x the first)" for path in ("networks", "record"))
        if row.get("rate_only"):
            print(f"{name}: CPU {row['cpu_samples_per_s']:.2f} samples/s (timed only); {tail}")
            continue
        for shape, r in row["shapes"].items():
            curve = " -> ".join(f"{p['error']:.2f}@{p['samples']}" for p in r["curve"])
            last = r["curve"][-1]["sets"]
            detail = "; ".join(f"{s} {f['mean_256']:.2f}/{f['median_256']:.2f} outline {f['outline_mean_256']:.2f} "
                               f"interior {f['interior_mean_256']:.2f} ratio {f['ratio_error']:.3f}" for s, f in last.items())
            b = r["budget"]
            detail += (f"; budget: R IoU {b['refiner_iou']:.3f}, S peaks (DARK) {b['s_peaks_dark_256']:.2f}, "
                       f"T alone {b['t_alone_256']:.2f}")
            print(f"{name} {shape}: {curve}; gain {r['gain_per_1k']:.2f} px/1k (last half {r['late_gain_per_1k']:.2f}); "
                  f"CPU {r['cpu_samples_per_s']:.1f} samples/s; {detail}; samples {r['samples']} [{r['samples_digest']}]")
        if "shape_accuracy" in row:
            print(f"{name} shape accuracy: " + ", ".join(f"{100 * a:.0f}%@{s}" for s, a in row["shape_accuracy"].items()))
        print(f"{name}: {tail}")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
