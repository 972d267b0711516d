"""A lease's evaluation: the campaign's models and the shipped ones on the same fixed masks.

The masks are `benchmarks/accuracy/bench_accuracy.py`'s validation sets (seeded 256 px spools:
clean `paper`, noisy `paper`, `street`, per shape), fitted through `infer`'s path, each model at
its own size; the figures are mean corner errors in 256 px units, networks only. The shipped
models' figures do not change from lease to lease (the same masks, the same files): they are
measured once and kept in campaign/eval-shipped.json.
"""
from __future__ import annotations

import json
import math
import logging
import subprocess
import sys
from pathlib import Path

from cuboidtrain.campaign.plan import CampaignPlan
from cuboidtrain.models.zoo import pack, shipped_path

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "benchmarks" / "accuracy" / "bench_accuracy.py"
SHIPPED_EVAL = "eval-shipped.json"


def pack_models(checkpoints: dict[str, Path], plan: CampaignPlan, folder: Path, recipe: str) -> dict[str, Path]:
    """Each shape's model file (weights, config, card: `cuboidtrain models pack`) of the lease's checkpoint."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {}
    for shape, checkpoint in checkpoints.items():
        files[shape] = folder / f"{shape}.pt"
        pack(checkpoint, files[shape], list(plan.scenes), recipe=recipe)
    return files


def bench(models: dict[str, Path], samples: int, spools: Path, threads: int, timeout_s: float, out: Path) -> dict | None:
    """bench_accuracy's JSON (also written to `out`) for `models` on `samples` masks a set, or None
    (a line in the log says why)."""
    command = [sys.executable, str(BENCH), "--checkpoint", *map(str, models.values()), "--samples", str(samples),
               "--spools", str(spools), "--threads", str(threads), "--latency-repeats", "0", "--no-eval", "--json", str(out)]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=max(timeout_s, 1), cwd=ROOT)
    except subprocess.TimeoutExpired:
        log.warning("evaluation of %s cut off after %.0f s (the lease's deadline)", ", ".join(map(str, models.values())), timeout_s)
        return None
    if done.returncode or not out.is_file():
        log.warning("evaluation of %s failed: %s", ", ".join(map(str, models.values())),
                    (done.stderr.strip().splitlines() or ["no message"])[-1])
        return None
    return finite(json.loads(out.read_text()))  # Python's json reads NaN; the one writer refuses it


def finite(data):
    """`data` with every NaN or Infinity (a figure with nothing to measure, as coverage of a model
    with no error bars) as None, the way the infer record writes one."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {key: finite(value) for key, value in data.items()}
    if isinstance(data, list):
        return [finite(value) for value in data]
    return data


def shipped_figures(campaign: Path, plan: CampaignPlan) -> dict | None:
    """The shipped models' figures kept from an earlier lease on the same masks (as many a set), else None."""
    path = Path(campaign) / SHIPPED_EVAL
    if not path.is_file():
        return None
    kept = finite(json.loads(path.read_text()))  # as bench's own figures: an older writer kept NaN
    wanted = {r["shape"] for r in kept.get("rows", [])}
    same = all(r["samples"] == plan.eval_samples for r in kept.get("rows", [])) and set(plan.shapes) <= wanted
    return kept if same else None


def evaluation_record(lease: int, steps: dict[str, list], where: str, date: str, compare: dict, scored: dict) -> dict:
    """campaign/eval.json: the newest evaluation of the standing state, with the lease and steps it belongs
    to and where it was measured (a lease's own, taken in by `apply`, or `campaign evaluate`'s here)."""
    return {"lease": lease, "steps": steps, "where": where, "date": date, "compare": compare} | scored


def shipped_models(plan: CampaignPlan) -> dict[str, Path]:
    return {shape: shipped_path(shape) for shape in plan.shapes}


def compare(campaign: dict | None, shipped: dict | None) -> dict:
    """`set/shape` -> the campaign's and the shipped models' mean corner error (256 px units), and
    how many sets the campaign wins (a lower error)."""
    figures: dict[str, dict] = {}
    for who, result in (("campaign", campaign), ("shipped", shipped)):
        for row in (result or {}).get("rows", []):
            figures.setdefault(f"{row['set']}/{row['shape']}", {})[who] = round(row["infer_mean_256"], 3)
    wins = sum(1 for f in figures.values() if "campaign" in f and "shipped" in f and f["campaign"] < f["shipped"])
    return {"sets": figures, "campaign_wins": wins, "compared": sum(1 for f in figures.values() if len(f) == 2)}
