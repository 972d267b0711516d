"""The one fit path, and the Python API: a Fitter fits masks, every command goes through it.

    from cuboidtrain import Fitter
    fit = Fitter.from_shipped().fit("mask.png")
    fit.keypoints, fit.ratios, fit.shape, fit.confidence

A Fitter is built once from models (the shipped ones, files, or CuboidNets in
hand) and one FitOptions, checked there. `fit` takes a mask image file or an
array and returns a `Fit`; `records` is `cuboidtrain infer`'s fitting: one outcome per
input, a `Fit` (per component) or, for an input that cannot be fitted, a `FitFailure`
while the others go on (`cuboidtrain.infer.records` writes them as docs/contract.md's
"The infer record"). `predict` runs the model's chain (`CuboidNet.forward`)
at the options' Refiner passes and reads the keypoints with the options' extractor,
for `eval`'s batches as for one framed mask. `report` and `localize` fit through
`fit` and `records`.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from cuboidtrain.models.device import one_thread, resolve_device
from cuboidtrain.fit.candidates import Candidate, Explanation, assess, choose
from cuboidtrain.models.codec import make_codec, render_heatmaps
from cuboidtrain.fit.cuboid import (FirstCuboid, FittedCuboid, NoCuboid, NonFiniteCuboid, astray, choose_cuboid,
                                   fit_candidates, first_cuboid, impossible, plausible, stopped_short)
from cuboidtrain.geometry import mask_fit
from cuboidtrain.geometry.outline import MaskTarget
from cuboidtrain.fit.masks import Framing, components, frame, load_mask, silhouette, to_mask, warp
from cuboidtrain.geometry.intrinsics import KnownCamera
from cuboidtrain.geometry.silhouette import confidence
from cuboidtrain.models.checkpoint import load_models
from cuboidtrain.models.classifier import ShapeClassifier
from cuboidtrain.models.networks import ChainOutput, CuboidNet
from cuboidtrain.models.refine import refine
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.fit.shape_call import ShapeCall, cached_classifier, call_shape, shipped_classifier
from cuboidtrain.fit.trust import Trust, judge, signs
from shared.errors import UsageError
from shared.files import non_finite
from shared.sample import signed
from shared.shapes import get_shape

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Fit:
    """One fitted component: the infer record's fields, typed (docs/contract.md, "The infer record")."""

    shape: str  # the chosen shape class, "box" or "twobox"
    keypoints: np.ndarray  # (N, 2) x, y in the input's pixels, pixel centres, in the contract's corner order
    ratios: dict[str, float]  # depth/height, width/height (and the twobox's part ratios)
    confidence: float  # IoU of the fitted silhouette with the input, lowered where corners are guessed
    refine_steps: int  # Refiner passes run
    refine_converged: bool
    warnings: tuple[str, ...] = ()
    candidates: dict[str, float] = field(default_factory=dict)  # every shape class tried -> its confidence
    input: str | None = None  # the file, when one was read
    component: int | None = None  # 0 = largest; set with FitOptions(all_components=True)
    cuboid: FittedCuboid | None = None  # with FitOptions(cuboid=True): the box whose projection is `keypoints`
    trust: Trust | None = None  # with the cuboid: how far to trust the fit, and why (`cuboidtrain.fit.trust`)
    shape_call: ShapeCall | None = None  # with the shape classifier: who called the class (`cuboidtrain.fit.shape_call`)
    # What an explanation draws (the winning candidate: refined mask, heat maps, framed input, Framing).
    explanation: Explanation | None = field(default=None, repr=False, compare=False)

    @property
    def keypoint_names(self) -> tuple[str, ...]:
        return tuple(get_shape(self.shape).keypoint_names)

    def record(self, with_component: bool = False) -> dict:
        """The JSON record `cuboidtrain infer` writes."""
        spread = {"ratios_sd": self.cuboid.ratios_sd()} if self.cuboid is not None else {}
        record = {"input": self.input, "shape": self.shape, "confidence": self.confidence,
                  "keypoints": np.asarray(self.keypoints).tolist(), "ratios": self.ratios, **spread,
                  "refine_steps": self.refine_steps, "refine_converged": self.refine_converged, "error": None,
                  "warnings": list(self.warnings), "candidates": self.candidates}
        if self.cuboid is not None:
            record["trust"] = None if self.trust is None else self.trust.record()
            record["cuboid"] = self.cuboid.record()
            record["shape_call"] = None if self.shape_call is None else self.shape_call.record()
        return record | ({"component": self.component} if with_component else {})


@dataclass(frozen=True)
class FitFailure:
    """An input that could not be fitted (unreadable, empty, a fit whose numbers are not finite): its
    infer record has `error` set to `reason` and no fit fields."""

    input: str  # the path or URL as given
    reason: str  # one line


Outcome = Fit | FitFailure  # what `records` gives for an input (a Fit per component)


@dataclass(frozen=True)
class Oracle:
    """Stages of the chain replaced by the truth for one input, in its pixels (the error budget:
    benchmarks/accuracy/bench_budget.py): the rest of the fit runs as `infer` runs it."""

    refined: np.ndarray | None = None  # (H, W) bool, the true clean mask: R's output, framed as the input is
    keypoints: np.ndarray | None = None  # (N, 2) px, the true corners: S's maps, Gaussians there (the training targets)

    def chain(self, model: CuboidNet, x1: torch.Tensor, steps: int | None, framing: Framing) -> ChainOutput:
        """T(S(R^K(x1))) with R's output and S's maps given where the oracle gives them."""
        if self.refined is None:
            refined, steps, converged = refine(model.refiner, x1, steps)
        else:
            framed = signed(warp(self.refined, framing, model.grey_input))
            refined, steps, converged = torch.from_numpy(framed)[None, None].to(x1.device), 0, True
        if self.keypoints is None:
            heatmaps = model.estimator(refined)
        elif len(self.keypoints) != get_shape(model.shape).num_keypoints:
            raise ValueError(f"oracle keypoints {np.shape(self.keypoints)}: expected the {model.shape} model's "
                             f"{get_shape(model.shape).num_keypoints} corners")
        else:
            true = torch.from_numpy(framing.to_model(self.keypoints))[None].to(x1.device)
            heatmaps = render_heatmaps(true, model.size, model.sigma)
        keypoints, ratios = model.tabulator(heatmaps)
        return ChainOutput(refined=refined, heatmaps=heatmaps, keypoints=keypoints, tabulated=keypoints,
                           ratios=ratios, refine_steps=steps, refine_converged=converged)


class NonFiniteFit(ValueError):
    """A model gave NaN or Infinity for a mask: no fit, and in `records` a FitFailure (its weights
    are a diverged training's, or the input broke its arithmetic)."""


class Fitter:
    """Models (at most one per shape class) and FitOptions; fits masks."""

    def __init__(self, models: Sequence[CuboidNet], options: FitOptions | None = None):
        self.options = (options or FitOptions()).validate()
        self.models = candidate_models(models, self.options.shape)
        self.device = resolve_device(self.options.device)
        self.codecs = {m.shape: make_codec(self.options.extractor, m, self.options.pdm_components)
                       for m in self.models}
        for model in self.models:
            model.to(self.device).eval()
        self.classifier = self._classifier()

    def _classifier(self) -> ShapeClassifier | None:
        """The shipped shape classifier where it has a class to call (the cuboid fit, box and twobox
        both tried) and the options ask for it; else None."""
        shapes = {m.shape for m in self.models}
        if not (self.options.shape_classifier and self.options.cuboid and {"box", "twobox"} <= shapes):
            return None
        if self.options.classifier_file is not None:
            return cached_classifier(Path(self.options.classifier_file))
        return shipped_classifier()

    @classmethod
    def from_files(cls, paths: Sequence[str | Path], options: FitOptions | None = None) -> "Fitter":
        """From checkpoints or model files; the options are checked before any file is read."""
        options = (options or FitOptions()).validate()
        return cls(load_models([Path(p) for p in paths]), options)

    @classmethod
    def from_shipped(cls, options: FitOptions | None = None) -> "Fitter":
        """From the shipped models (`cuboidtrain models`): box and twobox, or the one `options.shape` names."""
        from cuboidtrain.models.zoo import default_checkpoints

        options = (options or FitOptions()).validate()
        return cls.from_files(default_checkpoints(None, options.shapes), options)

    # --- fitting ---------------------------------------------------------------------------

    def fit(self, mask: str | Path | np.ndarray, camera: KnownCamera | None = None, oracle: Oracle | None = None) -> Fit:
        """The building of a mask image file, URL (`s3://...`, read by fsspec: `storage`) or array (H, W)
        (object > half its maximum, or `label_id`, `threshold`, `invert`: `masks.to_mask`): its pieces of at least 1% of the largest one's area,
        together (`masks.silhouette`); ValueError when it has none, or the file cannot be read.
        `camera`: what is known of its camera, in its pixels (else the options', `FitOptions.camera_for`);
        `oracle`: stages replaced by the truth (the error budget)."""
        return self._fit_parts(mask, all_components=False, camera=camera, oracle=oracle)[0]

    def fit_all(self, mask: str | Path | np.ndarray) -> list[Fit]:
        """One Fit per component (>= 16 px, largest first) with `all_components`, else `fit`'s one."""
        return self._fit_parts(mask, self.options.all_components)

    def outcomes(self, paths: Sequence[str | Path],
                explain: Callable[[int, str, Fit], Sequence[str]] | None = None) -> list[Outcome]:
        """`cuboidtrain infer`'s fits of the inputs, in input order: each input's Fit (one per component
        with `all_components`), without its explanation's arrays, or a FitFailure for an input that
        cannot be fitted, and the others still run. `explain(index, path, fit)` draws each fitted
        component (cuboidtrain.infer.explain.Explainer) and returns the warnings it adds to its Fit."""
        outcomes: list[Outcome] = []
        for index, path in enumerate(paths):
            try:
                fits = self.fit_all(path)
            except (ValueError, OSError, cv2.error) as exc:  # bad data: this input only
                outcomes.append(failure(path, " ".join(str(exc).split())))  # one line, whatever cv2 put in it
                continue
            outcomes += [settle(index, str(path), fitted, explain) for fitted in fits]
        return outcomes

    @torch.inference_mode()
    def predict(self, model: CuboidNet, x1: torch.Tensor, oracle: Oracle | None = None,
                framing: Framing | None = None) -> ChainOutput:
        """The chain T(S(R^K(x1))) on a (B, 1, S, S) +-1 batch, K the options' Refiner passes, its
        `keypoints` read by the options' extractor (`tabulated` keeps T's); with an `oracle`
        (one mask, its `framing`), the stages it gives replaced by the truth."""
        if oracle is not None and framing is None:
            raise ValueError("an oracle needs the framing: the map from the input's pixels to the model's")
        out = (model(x1.to(self.device), self.options.refine_steps) if oracle is None
               else oracle.chain(model, x1.to(self.device), self.options.refine_steps, framing))
        return replace(out, keypoints=self.codecs[model.shape].decode(out.heatmaps, out.tabulated).keypoints)

    def _read(self, mask: str | Path | np.ndarray) -> np.ndarray:
        if isinstance(mask, (str, Path)):
            return load_mask(mask, self.options.label_id, self.options.threshold, self.options.invert)  # a URL stays a string
        return to_mask(mask, self.options.label_id, threshold=self.options.threshold, invert=self.options.invert)

    def _fit_parts(self, mask, all_components: bool, camera: KnownCamera | None = None,
                   oracle: Oracle | None = None) -> list[Fit]:
        name = str(mask) if isinstance(mask, (str, Path)) else None
        mask = self._read(mask)
        if all_components:  # a mask of several objects: each fitted alone
            parts = components(mask, all_components=True)
        else:  # one building, maybe cut into pieces by an occluder: fitted whole
            building = silhouette(mask)
            parts = [] if building is None else [building]
        if not parts:
            raise UsageError(f"{name or 'mask'}: no component of at least 16 px")
        known = camera or (self.options.camera_for(name, mask.shape) if self.options.cuboid else None)
        fits = [self._fit_component(part, name, known, oracle) for part in parts]
        if all_components:
            fits = [replace(f, component=k) for k, f in enumerate(fits)]
        return fits

    def _fit_component(self, mask: np.ndarray, name: str | None, known: KnownCamera | None = None,
                       oracle: Oracle | None = None) -> Fit:
        """Frame one component for every candidate model and keep the best-explained fit,
        its keypoints mapped back to the input's pixels; with `cuboid`, each candidate's cuboid
        fitted to the component, judged by its own silhouette, and its projection kept (only the
        class a sure shape call names, where its cuboid is plausible: `first_cuboids`)."""
        call = call_shape(self.classifier, mask) if self.options.cuboid else None
        set_aside: list[str] = []
        if not self.options.cuboid:  # each candidate judged by its own keypoints' silhouette
            candidates = [self.fit_framed(model, *self.framed(model, mask), oracle) for model in self.models]
            firsts, cuboids = {}, {}
            best = choose(candidates)
        else:  # choose by how well each fitted cuboid explains the input, at its resolution, and is plausible
            # First without restarts, then only where the chosen class stopped short (`reached`), and with a
            # camera given, each class it led astray from the free camera's fit (`freed`)
            target = MaskTarget.of(mask)
            candidates, firsts = self.first_cuboids(mask, target, known, call, oracle)
            cuboids = {shape: first.cuboid for shape, first in firsts.items()}
            called = None if call is None else call.shape  # a rough mask's class, by the classifier
            best, set_aside = choose_cuboid(candidates, cuboids, called)
            if again := self.reached(best, firsts, cuboids, mask):
                cuboids |= again
                best, set_aside = choose_cuboid(candidates, cuboids, called)
            if known is not None and (freed := self.freed(candidates, cuboids, best, target, known)):
                firsts |= freed
                cuboids |= {shape: first.cuboid for shape, first in freed.items()}
                best, set_aside = choose_cuboid(candidates, cuboids, called)
            if calm := self.settled(best, firsts, cuboids, mask):  # a better fit of the same class, chosen again:
                cuboids[best.shape] = calm  # a set-aside class it now explains better than says so no more
                best, set_aside = choose_cuboid(candidates, cuboids, called)
            candidates = [replace(c, confidence=cuboids[c.shape].fit.iou) for c in candidates]
        cuboid = cuboids.get(best.shape)
        if cuboid is not None and cuboid is firsts[best.shape].cuboid:  # a first fit's: its error bars, for it alone
            cuboid = firsts[best.shape].with_error_bars()
        keypoints = best.framing.to_input(best.keypoints) if cuboid is None else cuboid.fit.keypoints
        scores = assess(best, mask, keypoints)
        trust = None if cuboid is None else self.trust(best, cuboid, cuboids, mask, call)
        return Fit(shape=best.shape, keypoints=keypoints, ratios=best.ratios if cuboid is None else cuboid.fit.ratios,
                   confidence=scores.confidence, refine_steps=best.refine_steps,
                   refine_converged=best.refine_converged,
                   warnings=scores.warnings + tuple(set_aside) + (() if trust is None else trust.lines()),
                   candidates={c.shape: c.confidence for c in candidates}, input=name, cuboid=cuboid, trust=trust,
                   shape_call=call,
                   explanation=Explanation(candidate=best, mask=mask))

    def first_cuboids(self, mask: np.ndarray, target: MaskTarget, known: KnownCamera | None, call: ShapeCall | None,
                      oracle: Oracle | None = None) -> tuple[list[Candidate], dict[str, FirstCuboid]]:
        """Each model's candidate for `mask` (its networks, `fit_framed`) and its cuboid from its first start
        (`first_cuboid`), the class the shape classifier's sure `call` names first; where that one is possible
        and plausible, it alone: the choice takes it whatever the others explain (`choose_cuboid`), and each
        other class's networks and fit cost a quarter of the record each. The candidates in the models'
        order, as many as were fitted."""
        called = None if call is None else call.shape
        candidates, firsts = {}, {}
        for model in sorted(self.models, key=lambda m: m.shape != called):  # the called class first
            candidate = self.fit_framed(model, *self.framed(model, mask), oracle, judged=False)  # its cuboid judges it
            candidates[model.shape], firsts[model.shape] = candidate, self.first_cuboid(candidate, target, known)
            if model.shape == called and plausible(firsts[called].cuboid.fit):
                break
        return [candidates[m.shape] for m in self.models if m.shape in candidates], firsts

    @staticmethod
    def trust(best: Candidate, cuboid: FittedCuboid, cuboids: dict[str, FittedCuboid], mask: np.ndarray,
              call: ShapeCall | None) -> Trust:
        """How far to trust the chosen fit (`trust.judge`): its signs beside the other classes' IoU (None where
        the classifier's sure call chose it alone: no other was fitted), and the shape classifier's call
        where it chose the class (the shape is then no guess, whatever the IoU says)."""
        chose = call if call is not None and call.shape == best.shape else None  # the classifier's call chose it
        others = [c.fit.iou for shape, c in cuboids.items() if shape != best.shape]
        return judge(signs(best, cuboid, mask, None if chose is not None and not others else others), chose)

    def framed(self, model: CuboidNet, mask: np.ndarray) -> tuple[np.ndarray, Framing]:
        """`mask`'s object framed as `model` reads it (`masks.frame`): at its own size, with the options'
        margin, bool or grey as it was trained (`grey_input`); `fit_framed` takes the pair."""
        return frame(mask, model.size, self.options.margin, model.grey_input)

    def fit_framed(self, model: CuboidNet, framed_mask: np.ndarray, framing: Framing | None = None,
                   oracle: Oracle | None = None, judged: bool = True) -> Candidate:
        """One framed (S, S) mask at model resolution, bool or grey (`masks.levels`) -> its Candidate:
        keypoints (N, 2) model px, ratios, confidence, refine passes, and what an explanation draws
        (refined, heatmaps). `framing`, the map back to the input's pixels, is carried along
        (`oracle`: `predict`'s); `judged=False`: its confidence left NaN, for a caller that judges it
        otherwise (the cuboid's IoU: a rasterisation that buys nothing there)."""
        if framed_mask.shape != (model.size, model.size):
            raise ValueError(f"framed mask {framed_mask.shape}: expected ({model.size}, {model.size}) for this model")
        x1 = torch.from_numpy(signed(framed_mask))[None, None]
        with one_thread(self.device):  # the same numbers however many threads this machine gives torch
            out = self.predict(model, x1, oracle, framing)
        return self.candidate(model, out, 0, framed_mask, framing, judged)

    def fit_cuboids(self, candidates: Sequence[Candidate], masks: Sequence[np.ndarray | MaskTarget],
                    known: Sequence[KnownCamera | None] | None = None,
                    reach: float | None = None) -> list[FittedCuboid | NoCuboid]:
        """Each candidate's cuboid fitted to its mask (H, W) bool at the input's resolution, by the
        options' optimizer, one shape class's rows solved as one batch (`cuboid.fit_candidates`): a
        component's shape classes for `fit`, a batch of samples for `eval`. NoCuboid where a fit
        is not finite. `known`: each mask's given camera, or None (fitted); `reach`: the IoU below which a
        clean mask's fit restarts (`mask_fit.reach_silhouette`)."""
        return fit_candidates(candidates, masks, optimizer=self.options.optimizer, known=known,
                              plausible=self.options.plausible_camera, reach=reach)

    def first_cuboid(self, candidate: Candidate, target: MaskTarget, known: KnownCamera | None = None) -> FirstCuboid:
        """A candidate's cuboid from its first start alone (`cuboid.first_cuboid`), by the options'
        optimizer; NonFiniteCuboid where it is not finite."""
        first = first_cuboid(candidate, target, self.options.optimizer, known, self.options.plausible_camera)
        if isinstance(first.cuboid, NoCuboid):
            raise NonFiniteCuboid(first.cuboid.reason)
        return first

    @staticmethod
    def settled(chosen: Candidate, firsts: dict[str, FirstCuboid], cuboids: dict[str, FittedCuboid],
                mask: np.ndarray) -> FittedCuboid | None:
        """The chosen class's cuboid of a clean mask (`mask_fit.polygonal`) settled on its silhouette
        (`FirstCuboid.settled_on_silhouette`: the outline's misses weighed alike on both sides), at length
        where it is still short of it after the restarts (`cuboid.stopped_short`), briefly where it reached
        it; after the choice, which it leaves as it is (it only explains the mask better). None where the
        mask is rough or the settling explains it no better."""
        if stopped_short(cuboids, chosen.shape, mask) is not None:
            return firsts[chosen.shape].settled_on_silhouette(cuboids[chosen.shape])
        if not mask_fit.polygonal(mask):
            return None
        return firsts[chosen.shape].settled_on_silhouette(cuboids[chosen.shape], short=False)

    def reached(self, chosen: Candidate, firsts: dict[str, FirstCuboid], cuboids: dict[str, FittedCuboid],
                mask: np.ndarray) -> dict[str, FittedCuboid]:
        """Where the chosen class's cuboid stopped short of a clean mask's silhouette (`cuboid.stopped_short`):
        it restarted to reach it, and every other class's short of RESTART_IOU (the chosen one may be the
        wrong class, its own fit having stopped short), from their first fits (`FirstCuboid.reached`);
        those whose silhouette then explains the mask better. Else nothing."""
        reach = stopped_short(cuboids, chosen.shape, mask)
        if reach is None:
            return {}
        again = {}
        for shape, first in firsts.items():
            if shape != chosen.shape and cuboids[shape].fit.iou >= mask_fit.RESTART_IOU:
                continue
            refit = first.reached(reach if shape == chosen.shape else mask_fit.RESTART_IOU)
            if isinstance(refit, FittedCuboid) and refit.fit.iou > cuboids[shape].fit.iou:
                again[shape] = refit
        return again

    def freed(self, candidates: Sequence[Candidate], cuboids: dict[str, FittedCuboid], chosen: Candidate,
              target: MaskTarget, known: KnownCamera) -> dict[str, FirstCuboid]:
        """With a camera given: each class's cuboid that went astray (`cuboid.astray`) fitted again from its
        free-camera fit's corners, where that is possible and explains the mask better (or the one it
        replaces was impossible). A far off-centre view (a building cropped from a wide photo: the principal
        point outside the crop) can leave the networks' corners no lift near the silhouette under the given
        camera where a free camera reaches it; the free fit's corners, a real cuboid's projection, lifted
        under the given camera start the fit near it (a clean generated twobox: IoU 0.37 -> 0.99)."""
        freed, lost = {}, astray(cuboids, chosen.shape, target.mask)
        for candidate in (c for c in candidates if c.shape in lost):
            shape = candidate.shape
            try:
                free = self.first_cuboid(candidate, target, None).cuboid.fit
                moved = replace(candidate, keypoints=candidate.framing.to_model(free.keypoints))
                again = self.first_cuboid(moved, target, known)
            except NonFiniteCuboid:  # no better start: the fit it has stands
                continue
            was = cuboids[shape].fit
            if impossible(again.cuboid.fit) is None and (impossible(was) is not None or again.cuboid.fit.iou > was.iou):
                freed[shape] = again
        return freed

    def candidate(self, model: CuboidNet, out: ChainOutput, row: int, framed_mask: np.ndarray,
                  framing: Framing | None = None, judged: bool = True) -> Candidate:
        """Row `row` of the chain's output for a batch of framed masks (`predict`) -> its Candidate,
        as `fit_framed` makes it for one mask (`eval` runs the networks batched, then fits each
        row's cuboid from here). NonFiniteFit where that row's output is not finite; `judged=False`:
        no confidence (NaN)."""
        keypoints = out.keypoints[row].double().cpu().numpy()
        geometry = get_shape(model.shape)
        if not (np.isfinite(keypoints).all() and torch.isfinite(out.ratios[row]).all()):
            raise NonFiniteFit(f"the {model.shape} model's output is not finite (NaN or Infinity in its keypoints or "
                               f"ratios): its weights are a diverged training's, or the mask broke it; no fit")
        return Candidate(
            shape=model.shape,
            keypoints=keypoints,
            ratios=geometry.ratio_dict(out.ratios[row].cpu().tolist()),
            confidence=confidence(geometry, keypoints, framed_mask >= 0.5) if judged else math.nan,  # half covered or more
            refine_steps=out.refine_steps,
            refine_converged=out.refine_converged,
            refined=out.refined[row, 0].float().cpu().numpy(),
            heatmaps=out.heatmaps[row].float().cpu().numpy(),
            framed=framed_mask,
            framing=framing,
        )


def candidate_models(models: Sequence[CuboidNet], shape: str) -> list[CuboidNet]:
    """The models to try for `shape`: all of them for auto, else the one of that class."""
    given = [m.shape for m in models]
    if len(set(given)) != len(given):
        raise UsageError(f"two models of the same shape class ({', '.join(given)}): give one per shape")
    chosen = [m for m in models if shape == "auto" or m.shape == shape]
    if not chosen:
        raise UsageError(f"--shape {shape}: no {shape} model among the checkpoints given "
                         f"({', '.join(given) or 'none'})")
    return chosen


def draw(explain, index: int, path: str, fit: Fit) -> tuple[str, ...]:
    """Call the explanation writer; the warnings it adds. A picture that cannot be made is a
    warning, never a lost record."""
    try:
        return tuple(explain(index, path, fit))
    except (OSError, ValueError, RuntimeError) as exc:  # a full disk, an unwritable folder, matplotlib
        warning = no_explanation(exc)
        log.warning("%s: %s", path, warning)
        return (warning,)


def settle(index: int, path: str, fitted: Fit, explain) -> Outcome:
    """A fitted component as `records` gives it: its warnings logged, drawn by `explain` (with the
    warnings that adds), its explanation's arrays dropped (a Fit crosses to the process that writes
    it: as light as its record); a FitFailure where a number of its record is not finite."""
    for warning in fitted.warnings:
        log.warning("%s: %s", path, warning)
    if explain is not None:
        fitted = replace(fitted, warnings=fitted.warnings + draw(explain, index, path, fitted))
    if (found := non_finite(fitted.record())) is not None:  # the contract's numbers are finite, or an error
        return failure(path, f"{path}: the fit's {found[0]} is {found[1]}: no fit")
    return replace(fitted, explanation=None)


def failure(path: str | Path, reason: str) -> FitFailure:
    """Input `path` could not be fitted, for `reason` (logged)."""
    log.warning("%s", reason)
    return FitFailure(str(path), reason)


def no_explanation(exc: Exception) -> str:
    """The record's warning for an explanation picture that could not be made, on one line."""
    return "no explanation: " + " ".join(str(exc).split())


class Writers:
    """Per-fit writers (an Explainer's pictures, a MeshWriter's files) as one `records` callback:
    each called in turn, one's failure a warning that does not stop the next; all their warnings.
    Picklable when they are: a `--workers` pool sends its workers a copy (pool.fit_groups)."""

    def __init__(self, *writers: Callable[[int, str, Fit], Sequence[str]]):
        self.writers = writers

    @classmethod
    def of(cls, *writers) -> "Writers | None":
        """The writers given (None: not asked for) as one callback, or None when there are none."""
        given = tuple(w for w in writers if w is not None)
        return cls(*given) if given else None

    def __call__(self, index: int, path: str, fit: Fit) -> tuple[str, ...]:
        return tuple(warning for writer in self.writers for warning in draw(writer, index, path, fit))
