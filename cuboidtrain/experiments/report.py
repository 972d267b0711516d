"""The report's experiments (paper section 4.1, Table 3, Figure 14 and our additions), as data.

Each experiment measures trained models on fixed samples and returns plain
dicts; `run_report` gathers them in a `ReportResults`, which
`cuboidtrain.experiments.report_figures` turns into REPORT.md, report.json and the plots.

- Table 3: the chain's mean keypoint error on clean validation masks for random
  weights, the trained model (phases 1 + 2), T replaced by a PDM, the phase 1
  model fine-tuned with the final loss only, and the networks trained end to end
  with the final loss only.
- Extractors: every keypoint extractor on the clean and the noisy spool.
- Figure 14: error against the level of contour noise (no occlusion).
- Occlusion: error against the occluded fraction (no contour noise).
- Refinement: error against the number of Refiner passes (Figure 7), noisy spool.
- Shape selection: `--shape auto`'s accuracy on a mixed box/twobox set.

Samples the sweeps need are drawn by the generator with fixed seeds into a
temporary spool, so the report is reproducible bit for bit.
"""
from __future__ import annotations

import logging
import tempfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from cuboidgen.config import PAPER
from cuboidgen.occluders import OccluderLibrary
from cuboidgen.synth import make_sample
from cuboidtrain.data.loader import LoaderBatch
from cuboidtrain.models.checkpoint import load_model
from cuboidtrain.models.device import resolve_device
from cuboidtrain.train.evaluate import load_batches, measure, report
from cuboidtrain.experiments.generated_pdm import with_pdm
from cuboidtrain.models.codec import make_codec
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.models.networks import CuboidNet, build_model
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.models.settings import EXTRACTORS
from shared.errors import UsageError
from shared.sample import encode
from shared.spool import SpoolWriter, check_spool

log = logging.getLogger(__name__)

NOISE_LEVELS = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0)  # contour noise std, px at 256 px (the generator's unit)
OCCLUSION_BINS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 1.0)  # occluded fraction of the silhouette
REFINE_STEPS = (0, 1, 2, 3, None)  # None: until the refined mask stops changing


@dataclass(frozen=True)
class ReportConfig:
    checkpoints: tuple[str, ...]  # the trained models (phase 1 + 2), one per shape class
    clean_spools: tuple[str, ...]  # Table 3's validation: no noise, no occlusion
    noisy_spools: tuple[str, ...] = ()  # the `paper` scene: occlusion and contour noise
    finetune: tuple[str, ...] = ()  # phase 1 models trained on with the final loss only
    e2e: tuple[str, ...] = ()  # models trained from random weights with the final loss only
    out: str = "reports"
    samples: int = 500  # per spool and model
    sweep_samples: int = 200  # per noise level and per shape for shape selection; twice this for occlusion
    seed: int = 0
    device: str = "cpu"

    def validate(self) -> "ReportConfig":
        if not self.checkpoints:
            raise UsageError("no --checkpoint: give the trained model of at least one shape class")
        if not self.clean_spools:
            raise UsageError("no --clean-spool: Table 3 is measured on clean validation masks")
        for name, value in (("--samples", self.samples), ("--sweep-samples", self.sweep_samples)):
            if value < 1:
                raise UsageError(f"{name} {value}: expected a positive number of samples")
        for spool in self.clean_spools + self.noisy_spools:
            check_spool(Path(spool))
        return self


@dataclass(frozen=True)
class ReportResults:
    """Every experiment's figures (`run_report`): the options they were measured with, each shape
    class's models (`models`) and figures (`shapes`), and shape selection's, given two or more
    classes of one size (else None). `to_dict` is report.json's object, key for key."""

    config: ReportConfig
    models: dict[str, dict]
    shapes: dict[str, dict]
    shape_selection: dict | None = None

    def to_dict(self) -> dict:
        """The JSON object of report.json: config, models, shapes, then shape_selection when measured."""
        data = {"config": asdict(self.config), "models": self.models, "shapes": self.shapes}
        if self.shape_selection is not None:
            data["shape_selection"] = self.shape_selection
        return data


def load_by_shape(paths: tuple[str, ...], role: str) -> dict[str, tuple[CuboidNet, dict, str]]:
    """{shape: (model, checkpoint dict, path)}, one per shape class."""
    models = {}
    for path in paths:
        model, ckpt = load_model(path)
        if model.shape in models:
            raise UsageError(f"{role} {path}: a second {model.shape!r} model ({models[model.shape][2]} is one already)")
        models[model.shape] = (model, ckpt, str(path))
    return models


def read_validation(spools: tuple[str, ...], model: CuboidNet, samples: int) -> tuple[list[LoaderBatch], str] | None:
    """The first `samples` samples of the model's shape and size from the first spool that has any."""
    for spool in spools:
        try:
            batches, _ = load_batches(Path(spool), model.shape, model.size, 32, samples)
        except ValueError as exc:  # no sample of this shape and size there: try the next spool
            log.info("report: %s", exc)
            continue
        return batches, spool
    return None


def mean_error(model: CuboidNet, batches: list[LoaderBatch], device, extractor: str = "tabulator",
               refine_steps: int | None = 1) -> dict:
    options = FitOptions(device=device, extractor=extractor, refine_steps=refine_steps)
    result = report(model, batches, {}, model.sigma, options)
    return {"mean_px_error": result.mean_px_error, "median_px_error": result.median_px_error,
            "refiner_iou": result.refiner_iou, "samples": result.samples,
            "mean_ratio_error": result.mean_ratio_error}


def table3(shape: str, model: CuboidNet, batches: list[LoaderBatch], device, finetune=None, e2e=None) -> list[dict]:
    """The paper's Table 3 rows for one shape class, in its order; a model not given is None."""
    rows = [
        ("random weights", build_model(shape, model.size, seed=0, sigma=model.sigma, arch=model.arch), "tabulator"),
        ("trained with rep. meaning", model, "tabulator"),
        ("trained with rep. meaning, T replaced with PDM", with_pdm(model), "pdm"),
        ("pre-trained with rep. meaning, trained without rep. meaning", finetune, "tabulator"),
        ("uninitialized, trained without rep. meaning", e2e, "tabulator"),
    ]
    return [{"configuration": name, **(mean_error(m, batches, device, extractor) if m is not None else {})}
            for name, m, extractor in rows]


def extractor_errors(model: CuboidNet, batches: list[LoaderBatch], device) -> dict[str, float]:
    return {name: mean_error(model, batches, device, name)["mean_px_error"] for name in EXTRACTORS}


def refinement_errors(model: CuboidNet, batches: list[LoaderBatch], device) -> list[dict]:
    return [{"refine_steps": "auto" if k is None else k, **mean_error(model, batches, device, refine_steps=k)}
            for k in REFINE_STEPS]


def generated_batches(folder: Path, shape: str, size: int, scene, count: int, seed: int,
                      library) -> tuple[list[LoaderBatch], dict[str, dict]]:
    """`count` samples drawn with seeds seed.. into a spool under `folder`, read back as batches,
    and each sample's drawn parameters by name."""
    folder.mkdir(parents=True)
    params = {}
    with SpoolWriter(folder, limit=0) as writer:
        for k in range(count):
            sample = make_sample(shape, scene, size, seed + k, library)
            params[writer.publish(encode(sample))] = sample.params
    batches, _ = load_batches(folder, shape, size, 32, count)
    return batches, params


def noise_sweep(model: CuboidNet, workdir: Path, count: int, seed: int, device, library) -> list[dict]:
    """Figure 14: the chain's error at fixed contour-noise levels, without occlusion."""
    rows = []
    for level in NOISE_LEVELS:
        scene = replace(PAPER, name=f"noise-{level}", occluders=(0, 0), contour_noise=(level, level))
        batches, _ = generated_batches(workdir / f"{model.shape}-noise-{level}", model.shape, model.size,
                                       scene, count, seed, library)
        rows.append({"contour_noise_256px": level, "contour_noise_px": level * model.size / 256,
                     **mean_error(model, batches, device)})
    return rows


def occlusion_sweep(model: CuboidNet, workdir: Path, count: int, seed: int, device, library) -> list[dict]:
    """Error against the occluded fraction of the silhouette, without contour noise."""
    scene = replace(PAPER, name="occlusion-only", occluders=(0, 4), contour_noise=(0.0, 0.0))
    batches, params = generated_batches(workdir / f"{model.shape}-occlusion", model.shape, model.size,
                                        scene, count, seed, library)
    errors = measure(model, batches, model.sigma, FitOptions(device=device))["keypoint"].double().mean(1).numpy()
    fractions = np.array([params[name]["occluded_fraction"] for batch in batches for name in batch.names])
    rows = []
    for low, high in zip(OCCLUSION_BINS[:-1], OCCLUSION_BINS[1:]):
        inside = (fractions >= low) & ((fractions < high) | (high == OCCLUSION_BINS[-1]))  # the last bin holds 1.0
        rows.append({"occluded_from": low, "occluded_to": high, "samples": int(inside.sum()),
                     "mean_px_error": float(errors[inside].mean()) if inside.any() else None})
    return rows


def shape_selection(models: dict[str, CuboidNet], count: int, seed: int, device, library) -> dict:
    """`--shape auto` on `count` noisy samples of each class, drawn at the models' size."""
    fitter = Fitter(list(models.values()), FitOptions(device=device))
    size = fitter.models[0].size
    confusion = {truth: dict.fromkeys(models, 0) for truth in models}
    for truth in models:
        for k in range(count):
            sample = make_sample(truth, PAPER, size, seed + k, library)
            confusion[truth][fitter.fit(sample.noisy).shape] += 1  # as infer: the building, its pieces together
    right = sum(confusion[s][s] for s in models)
    return {"samples": count * len(models), "accuracy": right / (count * len(models)), "confusion": confusion,
            "seeds": [seed, seed + count - 1]}


def run_report(config: ReportConfig) -> ReportResults:
    """Every experiment for every shape class given: the results REPORT.md is written from."""
    config = config.validate()
    device = resolve_device(config.device)
    main = load_by_shape(config.checkpoints, "--checkpoint")
    finetune, e2e = load_by_shape(config.finetune, "--finetune"), load_by_shape(config.e2e, "--e2e")
    check_ablations(main, {"--finetune": finetune, "--e2e": e2e})
    library = OccluderLibrary.load(None)
    models, shapes = {}, {}
    with tempfile.TemporaryDirectory(prefix="cuboid-report-") as tmp:
        for shape, (model, ckpt, path) in main.items():
            log.info("report: %s", shape)
            models[shape] = _describe(ckpt, path, finetune.get(shape), e2e.get(shape))
            pdm = make_codec("pdm", with_pdm(model))
            models[shape]["pdm"] = {"components": pdm.active, "variance_fraction": pdm.components}
            shapes[shape] = _shape_results(config, model, finetune.get(shape), e2e.get(shape), Path(tmp), library,
                                           device)
        selection = _selection(config, main, device, library)
    return ReportResults(config, models, shapes, selection)


def _selection(config: ReportConfig, main: dict, device, library) -> dict | None:
    """Shape selection's figures, given two or more shape classes of one size; else None."""
    if len(main) < 2 or len({m.size for m, _, _ in main.values()}) != 1:
        return None
    return shape_selection({s: m for s, (m, _, _) in main.items()}, config.sweep_samples, config.seed + 50_000,
                           device, library)


def check_ablations(main: dict, ablations: dict[str, dict]) -> None:
    """An ablation is measured on its trained model's samples: same shape class, size and sigma."""
    for role, models in ablations.items():
        for shape, (model, _, path) in models.items():
            if shape not in main:
                raise UsageError(f"{role} {path}: a {shape} model, but no --checkpoint of that shape to compare with")
            trained = main[shape][0]
            if (model.size, model.sigma) != (trained.size, trained.sigma):
                raise UsageError(f"{role} {path}: a {model.size} px model with sigma {model.sigma}, expected "
                                 f"{trained.size} px and sigma {trained.sigma} like {main[shape][2]}")


def _shape_results(config: ReportConfig, model: CuboidNet, finetune, e2e, workdir: Path, library,
                   device: torch.device) -> dict:
    clean = read_validation(config.clean_spools, model, config.samples)
    if clean is None:
        raise UsageError(f"no {model.shape} {model.size} px samples in any --clean-spool "
                         f"({', '.join(config.clean_spools)})")
    noisy = read_validation(config.noisy_spools, model, config.samples)
    out = {
        "clean_spool": clean[1],
        "table3": table3(model.shape, model, clean[0], device, finetune and finetune[0], e2e and e2e[0]),
        "extractors": {"clean": extractor_errors(model, clean[0], device)},
        "noise": noise_sweep(model, workdir, config.sweep_samples, config.seed + 10_000, device, library),
        "occlusion": occlusion_sweep(model, workdir, config.sweep_samples * 2, config.seed + 20_000, device, library),
    }
    if noisy is not None:
        out["noisy_spool"] = noisy[1]
        out["extractors"]["noisy"] = extractor_errors(model, noisy[0], device)
        out["refinement"] = refinement_errors(model, noisy[0], device)
    return out


def _describe(ckpt: dict, path: str, finetune, e2e) -> dict:
    """Which checkpoints made the figures, and how long each trained."""
    def one(entry):
        return None if entry is None else {"path": entry[2], "step": entry[1].get("step"),
                                           "phase": entry[1].get("config", {}).get("phase")}
    return {"trained": one((None, ckpt, path)), "finetune": one(finetune), "e2e": one(e2e),
            "size": ckpt["size"], "sigma": ckpt["sigma"]}
