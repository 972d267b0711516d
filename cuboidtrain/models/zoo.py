"""The shipped models: small weight files with a model card, used when no checkpoint is given.

A training checkpoint (`cuboidtrain run`'s last.pt) carries the optimizer, the
loader's position and every RNG so that a run resumes exactly; a *model file*
carries what a user loads: the weights (float16), the TrainConfig, and a card
saying how they were made (arch, size, scenes, steps, samples, wall time, commit,
validation figures). `pack` turns the one into the other. Both load through
`cuboidtrain.models.checkpoint.load_checkpoint`, so every `--checkpoint` option and
`--init` take either.

The shipped files live in `cuboidtrain/models/shipped/<shape>.pt` (package data, so a
plain `pip install` carries them), or in the folder `CUBOID_MODELS` names.
"""
from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import torch

from cuboidtrain.models.checkpoint import (FORMAT, MODEL_FORMAT, VERSION, checkpoint_arch, checkpoint_grey,
                                          checked_checkpoint, load_checkpoint, read_torch_file)
from cuboidtrain.models.classifier import CLASSIFIER_FORMAT, checked_classifier
from cuboidtrain.models.pdm import PointDistributionModel, spool_keypoints
from shared.errors import UsageError
from shared.files import atomic_path

SHIPPED_SHAPES = ("box", "twobox")
CLASSIFIER_FILE = "classifier.pt"  # the shape classifier's file in the models folder


def models_dir() -> Path:
    return Path(os.environ.get("CUBOID_MODELS") or Path(__file__).resolve().parent / "shipped")


def shipped_path(shape: str) -> Path:
    """The shipped model file of a shape class; a one-line error when it is missing."""
    if shape not in SHIPPED_SHAPES:
        raise UsageError(f"shape {shape!r}: shipped models exist for {', '.join(SHIPPED_SHAPES)}")
    path = models_dir() / f"{shape}.pt"
    if not path.is_file():
        raise UsageError(f"shipped model {path}: no such file (reinstall cuboid-fit, set CUBOID_MODELS, "
                         f"or give --checkpoint)")
    return path


def classifier_path() -> Path:
    """The shipped shape classifier (`cuboidtrain.models.classifier`), beside the shipped models."""
    return models_dir() / CLASSIFIER_FILE


def is_classifier(payload: object) -> bool:
    """Whether what a torch file holds (`read_torch_file`) is a shape classifier's (its `format`), not a
    model's or a checkpoint's."""
    return isinstance(payload, dict) and payload.get("format") == CLASSIFIER_FORMAT


def default_checkpoints(given: list[Path] | None, shapes: tuple[str, ...] = SHIPPED_SHAPES) -> list[Path]:
    """The checkpoints a command was given, else the shipped models of `shapes`."""
    return list(given) if given else [shipped_path(shape) for shape in shapes]


def init_lineage(checkpoint: dict) -> list[dict]:
    """The checkpoint and those it was initialised from (its config's `init`), newest first.
    Each still on disk adds its steps and wall time to the model card. A model file ends the
    lineage: its card already holds the phases before it (a continued shipped model)."""
    lineage, seen = [checkpoint], set()
    while ("card" not in lineage[-1] and (init := lineage[-1]["config"].get("init")) and init not in seen
           and Path(init).is_file()):
        seen.add(init)
        lineage.append(load_checkpoint(init))
    return lineage


def wall_time_s(run_folder: Path) -> float | None:
    """Seconds from the first to the last record of the run's metrics.jsonl, plus one logging interval."""
    try:
        lines = [json.loads(line) for line in (run_folder / "metrics.jsonl").read_text().splitlines() if line.strip()]
    except (OSError, ValueError):
        return None
    timed = [r for r in lines if "time" in r and "step_time_s" in r]
    if len(timed) < 2:
        return None
    return timed[-1]["time"] - timed[0]["time"] + timed[0]["step_time_s"] * timed[0]["step"]


def git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=10,
                             cwd=Path(__file__).resolve().parent)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def make_card(checkpoint_path: Path, checkpoint: dict, scenes: list[str], validation: dict | None,
              recipe: str | None) -> dict:
    lineage = init_lineage(checkpoint)
    config = checkpoint["config"]
    phases = []
    for ckpt in reversed(lineage):  # oldest first
        if "card" in ckpt:  # a model file this run continued: its phases, as its card tells them
            phases.extend(ckpt["card"]["phases"])
            continue
        c = ckpt["config"]
        folder = Path(c["out"])
        phases.append({"phase": c["phase"], "steps": ckpt["step"], "batch_size": c["batch_size"],
                       "samples": ckpt["step"] * c["batch_size"], "lr": c["lr"], "spool": c["spool"],
                       "wall_time_s": wall_time_s(folder), "threads": c.get("threads"), "device": c["device"]})
    return {
        "shape": checkpoint["shape"], "size": checkpoint["size"], "arch": checkpoint_arch(checkpoint),
        "sigma": checkpoint["sigma"], "scenes": scenes, "reframe": config.get("reframe", False),
        "grey_input": checkpoint_grey(checkpoint),
        "steps": sum(p["steps"] for p in phases), "samples_seen": sum(p["samples"] for p in phases),
        "wall_time_s": sum(p["wall_time_s"] or 0.0 for p in phases), "phases": phases,
        "commit": git_commit(), "packed_from": str(checkpoint_path), "recipe": recipe,
        "validation": validation or {},
    }


def pack(checkpoint_path: Path, out: Path, scenes: list[str], validation: dict | None = None,
         recipe: str | None = None, half: bool = True, pdm_spool: Path | None = None) -> dict:
    """Write the model file of a training checkpoint: weights (float16 unless `half` is
    False), config and card. Returns the card.

    With `pdm_spool` (the spool the model trained on), the point distribution model of
    `--extractor pdm` is fitted on its keypoint sets and saved in the file. A model file
    given with `pdm_spool` is packed again: its weights and card stay, its PDM is refitted.
    """
    checkpoint = load_checkpoint(checkpoint_path)
    if checkpoint["format"] == FORMAT:
        card = make_card(checkpoint_path, checkpoint, scenes, validation, recipe)
        weights = {k: v.half() if half and v.is_floating_point() else v for k, v in checkpoint["model"].items()}
        payload = {"format": MODEL_FORMAT, "version": VERSION, "shape": checkpoint["shape"],
                   "size": checkpoint["size"], "arch": card["arch"], "sigma": checkpoint["sigma"],
                   "config": checkpoint["config"], "step": checkpoint["step"], "model": weights, "card": card}
    elif pdm_spool is not None:
        payload, card = checkpoint, checkpoint["card"]
    else:
        raise UsageError(f"{checkpoint_path}: already a model file; pack a training checkpoint (last.pt), "
                         f"or give --pdm-spool to fit its shape model again")
    if pdm_spool is not None:
        sets = spool_keypoints(pdm_spool, checkpoint["shape"])
        payload["pdm"] = PointDistributionModel.fit(sets).to_dict()
        card["pdm"] = {"spool": str(pdm_spool), "keypoint_sets": len(sets)}
    with atomic_path(out) as tmp:
        torch.save(payload, tmp)
    return card


def validation_for(bench_json: Path, checkpoint_path: Path) -> dict:
    """The figures of `benchmarks/accuracy/bench_accuracy.py --json` that concern this checkpoint's shape class."""
    try:
        result = json.loads(Path(bench_json).read_text())
        shape = load_checkpoint(checkpoint_path)["shape"]
        figures = {row["set"]: {k: row[k] for k in ("infer_mean_256", "infer_median_256", "eval_mean_256", "samples")
                                if k in row}
                   for row in result["rows"] if row["shape"] == shape}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UsageError(f"--validation {bench_json}: not a bench_accuracy.py JSON ({exc})") from None
    return {"units": "mean corner error, px at 256 px, through infer", "sets": figures,
            "shape_selection": result.get("selection", {}), "benchmark": result.get("command")}


def cards(folder: Path | None = None) -> list[dict]:
    """The cards of the model files in `folder` (default the shipped ones), with their file and size."""
    folder = folder or models_dir()
    found = []
    for path in sorted(folder.glob("*.pt")):
        payload = read_torch_file(path, "model file", weights_only=False)  # read once, checked by its format
        if is_classifier(payload):  # whatever its name (`classifier train --out x.pt`)
            card = checked_classifier(path, payload)[1]
        else:
            model = checked_checkpoint(path, payload)
            card = model.get("card") or {"shape": model["shape"], "size": model["size"], "arch": checkpoint_arch(model)}
        found.append(card | {"file": str(path), "bytes": path.stat().st_size})
    return found
