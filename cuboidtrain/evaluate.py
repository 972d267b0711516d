"""Evaluation on a spool: the paper's average pixel error (Table 3) and what explains it.

The whole chain T(S(R^K(x1))) runs as infer runs it (`Fitter.predict`), in eval
mode, on the spool's samples of the model's shape class and size, in name
order, at the model's resolution. Beside
the paper's metric (mean Euclidean px distance between predicted and true
keypoints) it reports the median, PCK, the ratios' error, the Refiner's IoU and
the Tabulator alone on rendered heat maps x3, so a bad number can be traced to
the network that caused it. `evaluate_checkpoint` adds the paper's reference
row: the same networks with random weights, on the very same samples.
"""
from __future__ import annotations

import logging
from collections import Counter
from pathlib import Path

import torch

from cuboidtrain.models.checkpoint import load_model
from cuboidtrain.train.data import SKIP_REASONS, SpoolBatches, prepare_batch
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.models.refine import mask_iou
from cuboidtrain.models.networks import CuboidNet, build_model
from cuboidtrain.fit.options import DEFAULT_MARGIN, FitOptions
from shared.errors import UsageError
from shared.files import non_finite
from shared.sample import decode_record
from shared.shapes import get_shape
from shared.spool import check_spool, enumerate_spool, read_sample_bytes

log = logging.getLogger(__name__)

PCK_THRESHOLDS = (0.5, 1.0, 2.0, 5.0)  # px


def keypoint_errors(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """(B, N, 2), (B, N, 2) px -> (B, N) Euclidean distances in px."""
    if pred.shape != true.shape:
        raise ValueError(f"keypoints {tuple(pred.shape)} and {tuple(true.shape)}: expected equal (B, N, 2) shapes")
    return torch.linalg.vector_norm(pred.float() - true.float(), dim=-1)


def load_batches(spool: Path, shape: str, size: int, batch_size: int, max_samples: int | None,
                 margin: float = DEFAULT_MARGIN) -> tuple[list[dict], dict[str, int]]:
    """The first `max_samples` samples of this shape, in name order, as packed batches; samples of
    another size are framed at `size` as `infer` frames a mask, with `margin` (so a 256 px spool
    serves any model).

    Read once and kept, so two models can be evaluated on the very same samples
    even while a generator evicts from the spool. Returns the skip counts too.
    """
    reader, names = SpoolBatches(spool, shape, size, reframe="other-sizes", margin=margin), enumerate_spool(spool)
    wanted = len(names) if max_samples is None else max_samples
    batches, skipped, kept, position = [], dict.fromkeys(SKIP_REASONS, 0), 0, 0
    while kept < wanted and position < len(names):
        chunk = names[position : position + min(batch_size, wanted - kept)]  # never read past what is wanted
        position += len(chunk)
        batch = reader[chunk]
        for reason, count in batch["skipped"].items():
            skipped[reason] += count
        if batch["names"]:
            batches.append(batch)
            kept += len(batch["names"])
    if not kept:
        raise UsageError(_nothing_to_evaluate(spool, shape, size, names))
    if any(skipped.values()):
        log.info("evaluation on %s skipped %s", spool, {k: v for k, v in skipped.items() if v})
    return batches, skipped


def _nothing_to_evaluate(spool: Path, shape: str, size: int, names: list[str]) -> str:
    """The error for a spool without a usable sample: what it holds instead (only read on this path)."""
    if not names:
        return f"spool {spool}: empty, no {shape} {size} px samples to evaluate"
    found: Counter[str] = Counter()
    for name in names:
        data = read_sample_bytes(spool, name)
        try:
            found["vanished" if data is None else "{shape} {size} px".format(**decode_record(data))] += 1
        except ValueError:
            found["corrupt"] += 1
    held = ", ".join(f"{count} {what}" for what, count in found.most_common())
    return f"spool {spool}: 0 {shape} {size} px samples among {len(names)} ({held})"


@torch.inference_mode()
def _measure_batch(fitter: Fitter, model: CuboidNet, batch: dict, sigma: float) -> dict[str, torch.Tensor]:
    """Per-sample errors of one batch, on the CPU, the keypoints read as the Fitter reads them
    (T's, or its extractor's off S's heat maps)."""
    x = prepare_batch(batch, fitter.device, sigma, model.size)
    out = fitter.predict(model, x["x1"])  # the chain as infer runs it
    t_alone, _ = model.tabulator(x["x3"])  # T fed perfect heat maps: its own share of the error
    decoded_alone = fitter.codecs[model.shape].decode(x["x3"], t_alone).keypoints  # the extractor on perfect maps
    return {
        "keypoint": keypoint_errors(out.keypoints, x["x4"]).cpu(),  # (B, N)
        "ratio": (out.ratios.float() - x["ratios"]).abs().cpu(),  # (B, R)
        "iou": mask_iou(out.refined, x["x2"]).cpu(),  # (B,)
        "tabulator": keypoint_errors(t_alone, x["x4"]).cpu(),  # (B, N)
        "extractor": keypoint_errors(decoded_alone, x["x4"]).cpu(),  # (B, N)
    }


def measure(model: CuboidNet, batches: list[dict], sigma: float,
            options: FitOptions | None = None) -> dict[str, torch.Tensor]:
    """Per-sample errors over all batches (keypoint (S, N) px, ratio (S, R), iou (S,), ...), in
    the batches' order; the model's train/eval mode is restored afterwards."""
    was_training = model.training
    fitter = Fitter([model], options)  # on the options' device, in eval mode: BatchNorm on running statistics
    try:
        parts = [_measure_batch(fitter, model, batch, sigma) for batch in batches]
    finally:
        model.train(was_training)  # a trainer that validates mid-run keeps training in train mode
    return {key: torch.cat([p[key] for p in parts]) for key in parts[0]}


def _summarise(errors: dict[str, torch.Tensor], shape: str, thresholds) -> dict:
    geometry = get_shape(shape)
    px = errors["keypoint"].double()  # (S, N)
    return {
        "mean_px_error": px.mean().item(),
        "median_px_error": px.median().item(),
        "per_keypoint_px_error": dict(zip(geometry.keypoint_names, px.mean(0).tolist())),
        "pck": {str(float(t)): (px <= t).double().mean().item() for t in thresholds},
        "mean_ratio_error": errors["ratio"].double().mean().item(),
        "per_ratio_error": dict(zip(geometry.ratio_names, errors["ratio"].double().mean(0).tolist())),
        "refiner_iou": errors["iou"].double().mean().item(),
        "tabulator_px_error_on_true_heatmaps": errors["tabulator"].double().mean().item(),
        "extractor_px_error_on_true_heatmaps": errors["extractor"].double().mean().item(),
    }


def evaluate(model: CuboidNet, spool: Path, sigma: float, options: FitOptions | None = None,
             batch_size: int = 32, max_samples: int | None = None, pck_thresholds=PCK_THRESHOLDS) -> dict:
    """Metrics of `model` on the first `max_samples` samples of its shape and size in `spool`.

    Samples of another shape or size, corrupt or vanished ones are skipped and
    counted. ValueError when none is left, naming what the spool holds instead.
    """
    options = (options or FitOptions()).validate()
    spool = check_spool(spool)
    _check_counts(batch_size, max_samples)
    batches, skipped = load_batches(spool, model.shape, model.size, batch_size, max_samples, options.margin)
    return report(model, batches, skipped, sigma, options, pck_thresholds)


def report(model: CuboidNet, batches: list[dict], skipped: dict, sigma: float, options: FitOptions | None = None,
           thresholds=PCK_THRESHOLDS) -> dict:
    """The metrics of `model` on batches already read (`load_batches`)."""
    options = (options or FitOptions()).validate()
    errors = measure(model, batches, sigma, options)
    result = {"shape": model.shape, "size": model.size, "sigma": sigma, "samples": len(errors["iou"]),
              "extractor": options.extractor, "refine_steps": options.refine_steps, "skipped": skipped}
    result.update(_summarise(errors, model.shape, thresholds))
    if (found := non_finite(result)) is not None:  # never a nan in a table or a JSON as if it were a figure
        raise UsageError(f"evaluation of the {model.shape} model: {found[0]} is {found[1]}: its outputs are not "
                         f"finite (its weights are a diverged training's?); no metric to report")
    return result


def _check_counts(batch_size: int, max_samples: int | None) -> None:
    if batch_size < 1:
        raise UsageError(f"batch size {batch_size}: expected a positive integer")
    if max_samples is not None and max_samples < 1:
        raise UsageError(f"max samples {max_samples}: expected a positive integer or None (all)")


def evaluate_checkpoint(checkpoint: Path, spool: Path, options: FitOptions | None = None, batch_size: int = 32,
                        max_samples: int | None = None, random_init_seed: int = 0) -> dict:
    """`evaluate` for a saved model, plus Table 3's reference row: random weights on the same samples."""
    options = (options or FitOptions()).validate()  # before the model and the spool are read
    model, ckpt = load_model(checkpoint)
    spool = check_spool(spool)
    _check_counts(batch_size, max_samples)
    batches, skipped = load_batches(spool, model.shape, model.size, batch_size, max_samples, options.margin)
    result = report(model, batches, skipped, ckpt["sigma"], options)
    random_model = build_model(model.shape, model.size, seed=random_init_seed, sigma=ckpt["sigma"], arch=model.arch)
    random_model.pdm = model.pdm  # the same shape model: only the networks' weights differ
    baseline = report(random_model, batches, skipped, ckpt["sigma"], options)
    result.update({
        "random_init_mean_px_error": baseline["mean_px_error"],
        "random_init_median_px_error": baseline["median_px_error"],
        "random_init_seed": random_init_seed,
        "checkpoint": str(checkpoint),
        "step": ckpt.get("step"),
        "spool": str(spool),
    })
    return result


def format_report(result: dict) -> str:
    """A short plain-text table of an `evaluate` / `evaluate_checkpoint` result."""
    skipped = ", ".join(f"{n} {reason}" for reason, n in result["skipped"].items() if n) or "none"
    lines = []
    if "checkpoint" in result:
        lines.append(f"checkpoint   {result['checkpoint']} (step {result['step']}) on spool {result['spool']}")
    lines += [
        f"samples      {result['samples']} {result['shape']} {result['size']} px (skipped: {skipped})",
        f"keypoints    mean {result['mean_px_error']:.3f} px   median {result['median_px_error']:.3f} px",
    ]
    if "random_init_mean_px_error" in result:
        lines.append(f"random init  mean {result['random_init_mean_px_error']:.3f} px   "
                     f"median {result['random_init_median_px_error']:.3f} px")
    lines.append("PCK          " + "   ".join(f"@{t} px {v:.3f}" for t, v in result["pck"].items()))
    lines.append(f"T alone      {result['tabulator_px_error_on_true_heatmaps']:.3f} px on true heat maps")
    if result.get("extractor", "tabulator") != "tabulator":
        lines.append(f"extractor    {result['extractor']}: {result['extractor_px_error_on_true_heatmaps']:.3f} px "
                     f"on true heat maps")
    lines.append(f"R IoU        {result['refiner_iou']:.4f}")
    lines.append(f"ratios       mean abs error {result['mean_ratio_error']:.4f}")
    lines += [f"  {name:<22} {err:.4f}" for name, err in result["per_ratio_error"].items()]
    lines.append("per keypoint (px)")
    lines += [f"  {name:<22} {err:.3f}" for name, err in result["per_keypoint_px_error"].items()]
    return "\n".join(lines)
