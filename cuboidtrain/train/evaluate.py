"""Evaluation on a spool: the paper's average pixel error (Table 3) and what explains it.

The whole chain T(S(R^K(x1))) runs as infer runs it (`Fitter.predict`), in eval
mode, on the spool's samples of the model's shape class and size, in name
order, at the model's resolution. Beside
the paper's metric (mean Euclidean px distance between predicted and true
keypoints) it reports the median, PCK, the ratios' error, the Refiner's IoU and
the Tabulator alone on rendered heat maps x3, so a bad number can be traced to
the network that caused it. `evaluate_checkpoint` adds the paper's reference
row: the same networks with random weights, on the very same samples.

With `paths` (`cuboidtrain eval` always) it also scores the answer a user gets, per path,
in each sample's own px (a 256 px spool's, whatever the model's size), against the
sample's truth (`cuboidtrain.geometry.accuracy`: corners on the true hull against the hidden
interior ones, NME as a share of the building's span, ratio, yaw, 3D IoU and focal length
errors):

* `networks`: the chain's keypoints mapped back by the sample's framing, the Tabulator's
  ratios; it has no box, so its yaw and 3D IoU are those of its corners lifted
  (`cuboidtrain.geometry.lift.lift`);
* `cuboid`, with FitOptions(cuboid=True) (`eval --cuboid`): the cuboid fitted to the
  sample's own noisy mask from the same batch row by the Fitter's own calls (`Fitter.candidate`,
  then `Fitter.fit_cuboids`, as `infer --cuboid` fits a mask), a batch at once.

One pipeline: the networks run through `Fitter.predict`, each row becomes its Candidate by
`Fitter.candidate` and its cuboid by `Fitter.fit_cuboids`, the calls `infer` makes; only the
batching differs (a batch's samples are solved at once, one solver for all their starts, and
so are the lifts of the networks' corners, `lift.lift_many`).
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from cuboidtrain.models.checkpoint import load_model
from cuboidtrain.data.loader import SKIP_REASONS, LoaderBatch, Source, SpoolBatches
from cuboidtrain.data.prepare import prepare_batch
from cuboidtrain.fit.candidates import Candidate
from cuboidtrain.fit.cuboid import NoCuboid
from cuboidtrain.fit.fitter import Fitter, NonFiniteFit
from cuboidtrain.fit.masks import silhouette
from cuboidtrain.geometry.camera_params import CameraParams
from cuboidtrain.geometry.lift import lift_many
from cuboidtrain.geometry.accuracy import CornerErrors, Truth, against_truth, summarise
from cuboidtrain.models.refine import mask_iou
from cuboidtrain.models.networks import ChainOutput, CuboidNet, build_model
from cuboidtrain.fit.options import DEFAULT_MARGIN, FitOptions
from shared.errors import UsageError
from shared.files import non_finite
from shared.sample import decode_record
from shared.shapes import get_shape
from shared.spool import check_spool, enumerate_spool, read_sample_bytes

log = logging.getLogger(__name__)

PCK_THRESHOLDS = (0.5, 1.0, 2.0, 5.0)  # px
PATHS = ("networks", "cuboid", "cuboid_camera_given")  # the last: the generator's camera held (Truth.known_camera)


@dataclass(frozen=True)
class Reference:
    """Table 3's reference row beside a saved model's figures (`evaluate_checkpoint`): the same
    networks with random weights on the very same samples, and where the model came from."""

    random_init_mean_px_error: float
    random_init_median_px_error: float
    random_init_seed: int
    checkpoint: str
    step: int | None
    spool: str


@dataclass(frozen=True)
class Evaluation:
    """A model's figures on a spool (`evaluate`): the chain's keypoint error at model resolution and
    what explains it; with paths, each path's figures in the samples' own px (`summarise_paths`).
    `to_dict` is `eval --json`'s object, key for key."""

    shape: str
    size: int
    sigma: float
    samples: int
    extractor: str
    refine_steps: int | None
    skipped: dict[str, int]
    mean_px_error: float
    median_px_error: float
    per_keypoint_px_error: dict[str, float]
    pck: dict[str, float]  # threshold px (as a string) -> share of keypoints within it
    mean_ratio_error: float
    per_ratio_error: dict[str, float]
    refiner_iou: float
    tabulator_px_error_on_true_heatmaps: float
    extractor_px_error_on_true_heatmaps: float
    paths: dict[str, dict] | None = None  # path name -> `summarise_paths` figures
    reference: Reference | None = None

    def to_dict(self) -> dict:
        figures = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("paths", "reference")}
        return (figures | ({"paths": self.paths} if self.paths is not None else {})
                | (asdict(self.reference) if self.reference is not None else {}))


def keypoint_errors(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """(B, N, 2), (B, N, 2) px -> (B, N) Euclidean distances in px."""
    if pred.shape != true.shape:
        raise ValueError(f"keypoints {tuple(pred.shape)} and {tuple(true.shape)}: expected equal (B, N, 2) shapes")
    return torch.linalg.vector_norm(pred.float() - true.float(), dim=-1)


def load_batches(spool: Path, shape: str, size: int, batch_size: int, max_samples: int | None,
                 margin: float = DEFAULT_MARGIN, keep_sources: bool = False) -> tuple[list[LoaderBatch], dict[str, int]]:
    """The first `max_samples` samples of this shape, in name order, as packed batches; samples of
    another size are framed at `size` as `infer` frames a mask, with `margin` (so a 256 px spool
    serves any model). `keep_sources`: each batch also holds its samples as read and their
    framings (`sources`, what `paths` scores against).

    Read once and kept, so two models can be evaluated on the very same samples
    even while a generator evicts from the spool. Returns the skip counts too.
    """
    reader = SpoolBatches(spool, shape, size, reframe="other-sizes", margin=margin, keep_sources=keep_sources)
    names = enumerate_spool(spool)
    wanted = len(names) if max_samples is None else max_samples
    batches, skipped, kept, position = [], dict.fromkeys(SKIP_REASONS, 0), 0, 0
    while kept < wanted and position < len(names):
        chunk = names[position : position + min(batch_size, wanted - kept)]  # never read past what is wanted
        position += len(chunk)
        batch = reader[chunk]
        for reason, count in batch.skipped.items():
            skipped[reason] += count
        if batch.names:
            batches.append(batch)
            kept += len(batch.names)
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
def _measure_batch(fitter: Fitter, model: CuboidNet, batch: LoaderBatch, sigma: float,
                   paths: bool = False) -> tuple[dict[str, torch.Tensor], dict[str, list]]:
    """Per-sample errors of one batch, on the CPU, the keypoints read as the Fitter reads them
    (T's, or its extractor's off S's heat maps); with `paths`, each path's scores too."""
    x = prepare_batch(batch, fitter.device, sigma, model.size, model.grey_input)
    out = fitter.predict(model, x.x1)  # the chain as infer runs it
    t_alone, _ = model.tabulator(x.x3)  # T fed perfect heat maps: its own share of the error
    decoded_alone = fitter.codecs[model.shape].decode(x.x3, t_alone).keypoints  # the extractor on perfect maps
    errors = {
        "keypoint": keypoint_errors(out.keypoints, x.x4).cpu(),  # (B, N)
        "ratio": (out.ratios.float() - x.ratios).abs().cpu(),  # (B, R)
        "iou": mask_iou(out.refined, x.x2).cpu(),  # (B,)
        "tabulator": keypoint_errors(t_alone, x.x4).cpu(),  # (B, N)
        "extractor": keypoint_errors(decoded_alone, x.x4).cpu(),  # (B, N)
    }
    if not paths:
        return errors, {}
    if batch.sources is None:
        raise ValueError("scoring the paths needs the samples as read: load_batches(..., keep_sources=True)")
    framed = model_inputs(x.x1, model.grey_input)
    return errors, score_paths(fitter, model, out, framed, batch.sources)


def model_inputs(x1: torch.Tensor, grey: bool) -> np.ndarray:
    """(B, S, S) the framed masks as `infer` hands them to `Fitter.candidate`, from the batch's +-1 input
    (B, 1, S, S): each pixel's covered share for a grey-input model, else the object (x1 > 0)."""
    values = x1[:, 0].float().cpu().numpy()
    return (values + 1) / 2 if grey else values > 0


def score_paths(fitter: Fitter, model: CuboidNet, out: ChainOutput, framed: np.ndarray,
                sources: list[Source]) -> dict[str, list[CornerErrors | None]]:
    """Each path's scores (`cuboidtrain.geometry.accuracy.against_truth`) for the rows of one batch's chain output (`Fitter.predict`
    on the framed masks (B, S, S)); None where a path gave no answer (a non-finite output, a
    failed cuboid fit). The cuboid paths only with the Fitter's options' `cuboid`: the camera
    fitted, and given (the generator's, where the sample says it)."""
    scored: dict[str, list] = {name: [] for name in PATHS[: 3 if fitter.options.cuboid else 1]}
    candidates: list[Candidate | None] = []
    truths = [Truth.of_sample(source.sample) for source in sources]
    for row, source in enumerate(sources):
        try:
            candidates.append(fitter.candidate(model, out, row, framed[row], source.framing))
        except NonFiniteFit:
            candidates.append(None)
    keypoints = [None if c is None else s.framing.to_input(c.keypoints) for c, s in zip(candidates, sources)]
    cameras = _lifted(keypoints, truths, model.shape)
    scored["networks"] = [None if k is None else against_truth(k, c.ratios, t, cameras.get(row))
                          for row, (k, c, t) in enumerate(zip(keypoints, candidates, truths))]
    if fitter.options.cuboid:
        scored["cuboid"] = _cuboid_scores(fitter, candidates, sources, truths)
        scored["cuboid_camera_given"] = _cuboid_scores(fitter, candidates, sources, truths, given=True)
    return scored


def _lifted(keypoints: list[np.ndarray | None], truths: list[Truth], shape: str) -> dict[int, CameraParams]:
    """The networks' corners lifted to a cuboid (they have no box of their own), a batch's at once
    (`lift.lift_many`), for the rows whose truth has a camera to compare with."""
    rows = [row for row, (k, t) in enumerate(zip(keypoints, truths)) if k is not None and t.camera is not None]
    if not rows:
        return {}
    lifted = lift_many(np.array([keypoints[row] for row in rows]), get_shape(shape))
    return {row: one.camera for row, one in zip(rows, lifted)}


def _cuboid_scores(fitter: Fitter, candidates: list[Candidate | None], sources: list[Source],
                   truths: list[Truth], given: bool = False) -> list[CornerErrors | None]:
    """The cuboid of each candidate fitted to its sample's own noisy mask, the building's pieces
    together (what `Fitter` fits: `masks.silhouette`), the batch's fits solved at once by the
    call `infer` makes (`Fitter.fit_cuboids`), and scored; None where there is no fit. `given`:
    each sample's true camera held (None where the sample does not say it: not scored)."""
    masks = [None if c is None else silhouette(s.sample.noisy) for c, s in zip(candidates, sources)]
    known = [t.known_camera() if given else None for t in truths]
    fittable = [i for i, m in enumerate(masks) if m is not None and (known[i] is not None or not given)]
    fitted = dict(zip(fittable, fitter.fit_cuboids([candidates[i] for i in fittable], [masks[i] for i in fittable],
                                                   [known[i] for i in fittable])))
    scores: list[CornerErrors | None] = []
    for i, truth in enumerate(truths):
        fit = fitted.get(i)
        if fit is None or isinstance(fit, NoCuboid):
            scores.append(None)
            continue
        scores.append(against_truth(fit.fit.keypoints, fit.fit.ratios, truth, fit.fit.camera, fit.fit.spread))
    return scores


def measure(model: CuboidNet, batches: list[LoaderBatch], sigma: float, options: FitOptions | None = None,
            paths: bool = False) -> dict:
    """Per-sample errors over all batches (keypoint (S, N) px, ratio (S, R), iou (S,), ...), in
    the batches' order; with `paths` (batches read with their sources), `paths` too: each path's
    list of `where.CornerErrors` (None where it gave no answer). The model's train/eval mode is
    restored afterwards."""
    was_training = model.training
    fitter = Fitter([model], options)  # on the options' device, in eval mode: BatchNorm on running statistics
    try:
        parts = [_measure_batch(fitter, model, batch, sigma, paths) for batch in batches]
    finally:
        model.train(was_training)  # a trainer that validates mid-run keeps training in train mode
    errors = {key: torch.cat([p[0][key] for p in parts]) for key in parts[0][0]}
    if paths:
        errors["paths"] = {name: [e for p in parts for e in p[1][name]] for name in parts[0][1]}
    return errors


def _summarise(errors: dict[str, torch.Tensor], shape: str, thresholds) -> dict[str, float | dict[str, float]]:
    """The chain's figures: Evaluation's fields from `mean_px_error` on."""
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


def summarise_paths(scored: dict[str, list[CornerErrors | None]]) -> dict[str, dict]:
    """Per path: samples, failed (no answer), corner mean / median px (all corners pooled) and
    `where.summarise`'s figures; a figure without data (no interior corner, no answer) is None."""
    result = {}
    for name, errors in scored.items():
        answered = [e for e in errors if e is not None]
        corners = np.concatenate([np.concatenate([e.hull, e.interior]) for e in answered]) if answered else np.zeros(0)
        figures = {"samples": len(errors), "failed": len(errors) - len(answered),
                   "mean_px": float(corners.mean()) if len(corners) else math.nan,
                   "median_px": float(np.median(corners)) if len(corners) else math.nan} | summarise(answered)
        result[name] = {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in figures.items()}
    return result


def evaluate(model: CuboidNet, spool: Path, sigma: float, options: FitOptions | None = None,
             batch_size: int = 32, max_samples: int | None = None, pck_thresholds=PCK_THRESHOLDS,
             paths: bool = False) -> Evaluation:
    """Metrics of `model` on the first `max_samples` samples of its shape and size in `spool`;
    with `paths`, each path's figures in the samples' own px (`paths`: networks, and cuboid
    with `options.cuboid`).

    Samples of another shape or size, corrupt or vanished ones are skipped and
    counted. ValueError when none is left, naming what the spool holds instead.
    """
    options = (options or FitOptions()).validate()
    spool = check_spool(spool)
    _check_counts(batch_size, max_samples)
    batches, skipped = load_batches(spool, model.shape, model.size, batch_size, max_samples, options.margin, paths)
    return report(model, batches, skipped, sigma, options, pck_thresholds, paths)


def report(model: CuboidNet, batches: list[LoaderBatch], skipped: dict, sigma: float, options: FitOptions | None = None,
           thresholds=PCK_THRESHOLDS, paths: bool = False) -> Evaluation:
    """The metrics of `model` on batches already read (`load_batches`; with `keep_sources` for `paths`)."""
    options = (options or FitOptions()).validate()
    errors = measure(model, batches, sigma, options, paths)
    result = Evaluation(shape=model.shape, size=model.size, sigma=sigma, samples=len(errors["iou"]),
                        extractor=options.extractor, refine_steps=options.refine_steps, skipped=skipped,
                        **_summarise(errors, model.shape, thresholds),
                        paths=summarise_paths(errors["paths"]) if paths else None)
    if (found := non_finite(result.to_dict())) is not None:  # never a nan in a table or a JSON as if it were a figure
        raise UsageError(f"evaluation of the {model.shape} model: {found[0]} is {found[1]}: its outputs are not "
                         f"finite (its weights are a diverged training's?); no metric to report")
    return result


def _check_counts(batch_size: int, max_samples: int | None) -> None:
    if batch_size < 1:
        raise UsageError(f"batch size {batch_size}: expected a positive integer")
    if max_samples is not None and max_samples < 1:
        raise UsageError(f"max samples {max_samples}: expected a positive integer or None (all)")


def evaluate_checkpoint(checkpoint: Path, spool: Path, options: FitOptions | None = None, batch_size: int = 32,
                        max_samples: int | None = None, random_init_seed: int = 0, paths: bool = True) -> Evaluation:
    """`evaluate` for a saved model (with `paths`), plus Table 3's reference row: random weights on
    the same samples (its figures only)."""
    options = (options or FitOptions()).validate()  # before the model and the spool are read
    model, ckpt = load_model(checkpoint)
    spool = check_spool(spool)
    _check_counts(batch_size, max_samples)
    batches, skipped = load_batches(spool, model.shape, model.size, batch_size, max_samples, options.margin, paths)
    result = report(model, batches, skipped, ckpt["sigma"], options, paths=paths)
    random_model = build_model(model.shape, model.size, seed=random_init_seed, sigma=ckpt["sigma"], arch=model.arch)
    random_model.pdm = model.pdm  # the same shape model: only the networks' weights differ
    baseline = report(random_model, batches, skipped, ckpt["sigma"], replace(options, cuboid=False))
    return replace(result, reference=Reference(baseline.mean_px_error, baseline.median_px_error, random_init_seed,
                                               str(checkpoint), ckpt.get("step"), str(spool)))


def format_report(result: Evaluation) -> str:
    """A short plain-text table of an `evaluate` / `evaluate_checkpoint` result."""
    skipped = ", ".join(f"{n} {reason}" for reason, n in result.skipped.items() if n) or "none"
    ref, lines = result.reference, []
    if ref is not None:
        lines.append(f"checkpoint   {ref.checkpoint} (step {ref.step}) on spool {ref.spool}")
    lines += [
        f"samples      {result.samples} {result.shape} {result.size} px (skipped: {skipped})",
        f"keypoints    mean {result.mean_px_error:.3f} px   median {result.median_px_error:.3f} px",
    ]
    if ref is not None:
        lines.append(f"random init  mean {ref.random_init_mean_px_error:.3f} px   "
                     f"median {ref.random_init_median_px_error:.3f} px")
    lines.append("PCK          " + "   ".join(f"@{t} px {v:.3f}" for t, v in result.pck.items()))
    lines.append(f"T alone      {result.tabulator_px_error_on_true_heatmaps:.3f} px on true heat maps")
    if result.extractor != "tabulator":
        lines.append(f"extractor    {result.extractor}: {result.extractor_px_error_on_true_heatmaps:.3f} px "
                     f"on true heat maps")
    lines.append(f"R IoU        {result.refiner_iou:.4f}")
    lines.append(f"ratios       mean abs error {result.mean_ratio_error:.4f}")
    lines += [f"  {name:<22} {err:.4f}" for name, err in result.per_ratio_error.items()]
    lines.append("per keypoint (px)")
    lines += [f"  {name:<22} {err:.3f}" for name, err in result.per_keypoint_px_error.items()]
    if result.paths is not None:
        lines += format_paths(result.paths)
    return "\n".join(lines)


# A figure a path does not have, and why, in a word or two (`eval` prints nothing it cannot explain):
# the networks' corners are free points, so the camera of their lift is no camera (its focal length
# was off by 2150%), and they carry no error bars; the camera-given fit holds the true focal length.
NOT_APPLICABLE = {("focal length rel %", "networks"): "n/a: free corners",
                  ("truth in 1 / 2 sd %", "networks"): "n/a: no sd",
                  ("focal length rel %", "cuboid_camera_given"): "given"}
NO_DATA = "n/a: no data"  # no answer, or none of its kind (no interior corner, no true camera)


def format_paths(paths: dict[str, dict]) -> list[str]:
    """The paths side by side: mean / median of each figure (`summarise_paths`); a figure a path
    does not have says why (`NOT_APPLICABLE`, `NO_DATA`)."""
    def pair(figures, key, scale=1.0, digits=2, unit=""):
        mean, median = figures[f"{key}_mean{unit}"], figures[f"{key}_median{unit}"]
        return None if mean is None else f"{scale * mean:.{digits}f} / {scale * median:.{digits}f}"

    rows = [("answered", lambda f: f"{f['samples'] - f['failed']} of {f['samples']}"),
            ("corners px", lambda f: None if f["mean_px"] is None else f"{f['mean_px']:.2f} / {f['median_px']:.2f}"),
            ("hull corners px", lambda f: pair(f, "hull", unit="_px")),
            ("interior corners px", lambda f: pair(f, "interior", unit="_px")),
            ("NME % of span", lambda f: pair(f, "nme", 100)),
            ("depth/height rel %", lambda f: pair(f, "depth_height", 100, 1, "_rel")),
            ("width/height rel %", lambda f: pair(f, "width_height", 100, 1, "_rel")),
            ("yaw error deg", lambda f: pair(f, "yaw", unit="_deg")),
            ("3D IoU", lambda f: pair(f, "iou3d", digits=3)),
            ("focal length rel %", lambda f: pair(f, "focal", 100, 1, "_rel")),
            ("truth in 1 / 2 sd %", lambda f: None if f.get("within_1sd") is None
             else f"{100 * f['within_1sd']:.0f} / {100 * f['within_2sd']:.0f}")]
    names = list(paths)

    def cell(label, show, name) -> str:
        return NOT_APPLICABLE.get((label, name)) or show(paths[name]) or NO_DATA

    lines = ["paths        in the samples' own px, mean / median; networks' yaw and 3D IoU: its corners lifted",
             f"  {'':<22}" + "".join(f"{name:<20}" for name in names)]
    lines += [f"  {label:<22}" + "".join(f"{cell(label, show, name):<20}" for name in names) for label, show in rows]
    if "networks" in names:
        lines.append("  n/a: free corners: the networks' corners lifted have no camera of their own; no sd: no error bars")
    return lines
