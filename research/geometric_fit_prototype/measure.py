"""Tables for the mask fit (steps 3-4). Run from /work/frozen with OMP_NUM_THREADS=1:

    .venv/bin/python /work/proto20/measure.py exact N      # clean masks, true corners + 3 px noise as the start
    .venv/bin/python /work/proto20/measure.py networks N   # the shipped networks' corners (both shapes) + selection
"""
from __future__ import annotations

import sys
import time
import warnings

sys.path[:0] = ["/work/frozen", "/work/proto20"]
warnings.simplefilter("ignore")

import cv2
import numpy as np
import torch

import cuboid
from cuboidgen.config import SCENES
from cuboidgen.synth import make_sample
from shared.shapes import get_shape

torch.set_num_threads(1)
CELLS = [(s, n) for s in ("paper-clean", "paper", "street") for n in ("box", "twobox")]


def hull_corners(points: np.ndarray, tolerance: float = 0.25) -> np.ndarray:
    """Which corners are vertices of the points' convex hull (within `tolerance` px of one)."""
    hull = cv2.convexHull(points.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    return np.array([np.linalg.norm(hull - p, axis=1).min() <= tolerance for p in points])


def corner_errors(pred: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    err = np.linalg.norm(pred - truth, axis=1)
    on_hull = hull_corners(truth)
    return err[on_hull], err[~on_hull]


class Tally:
    def __init__(self):
        self.hull, self.interior, self.dh, self.wh, self.ms = [], [], [], [], []

    def add(self, pred, truth, ratios, true_ratios, ms):
        h, i = corner_errors(pred, truth)
        self.hull += h.tolist(); self.interior += i.tolist(); self.ms.append(ms)
        rel = np.abs(np.asarray(ratios) / true_ratios - 1)
        self.dh += rel[0::2].tolist(); self.wh += rel[1::2].tolist()

    def row(self) -> str:
        allc = self.hull + self.interior
        f = lambda v: f"{np.mean(v):.2f} / {np.median(v):.2f}" if v else "-"
        return (f"{f(allc)} | {f(self.hull)} | {f(self.interior)} | {100 * np.median(self.dh):.1f}% | "
                f"{100 * np.median(self.wh):.1f}% | {np.median(self.ms):.1f}")


HEADER = ("| scene | shape | method | n | all mean/med px | hull mean/med | interior mean/med | "
          "d/h med rel | w/h med rel | ms med |\n|---|---|---|---|---|---|---|---|---|---|")


def exact(n: int) -> None:
    """Clean silhouettes; start = lift of the true corners + 3 px Gaussian noise (confidence 1)."""
    print(HEADER)
    for scene, name in CELLS[:2] + CELLS[4:]:
        shape = get_shape(name)
        rng = np.random.default_rng(7)
        start, fitted = Tally(), Tally()
        for seed in range(n):
            s = make_sample(name, SCENES[scene], 256, 1000 + seed, LIB)
            noisy = s.keypoints + rng.normal(0, 3, s.keypoints.shape)
            truth_r = shape.ratio_vector(s.ratios)
            t1 = time.perf_counter()
            fit = cuboid.fit_mask(s.clean, shape, noisy, np.ones(len(noisy)))
            t2 = time.perf_counter()
            start.add(noisy, s.keypoints, truth_r * np.nan, truth_r, 0)
            fitted.add(fit.keypoints, s.keypoints, fit.camera.ratios(), truth_r, 1e3 * (t2 - t1))
        print(f"| {scene} (clean mask) | {name} | corners+3px (input) | {n} | {start.row()} |")
        print(f"| {scene} (clean mask) | {name} | mask fit | {n} | {fitted.row()} |", flush=True)


LIB = None
RATIO_WEIGHT = float(sys.argv[3]) if len(sys.argv) > 3 else 0.0  # pull toward the network's ratio head


def network_corners(fitter, mask: np.ndarray) -> dict:
    """Per shape model: corners in input px, per-corner confidence (heat-map peak), and the time."""
    from cuboidtrain.masks import frame, silhouette

    building = silhouette(mask)
    out = {}
    for model in fitter.models:
        t0 = time.perf_counter()
        framed, framing = frame(building, model.size, fitter.options.margin)
        res = fitter.fit_framed(model, framed)
        peaks = res["heatmaps"].reshape(len(res["heatmaps"]), -1).max(1)
        out[model.shape] = (framing.to_input(res["keypoints"]), np.clip(peaks, 0.05, 1.0), res["ratios"],
                            res["confidence"], 1e3 * (time.perf_counter() - t0))
    return out


def networks(n: int) -> None:
    """Shipped networks' corners -> mask fit on the noisy input, both shapes; selection by the fits."""
    from cuboidtrain import FitOptions, Fitter
    from cuboidtrain.infer import RICHER_SHAPE_MARGIN

    fitter = Fitter.from_shipped(FitOptions(device="cpu"))
    print(HEADER)
    for scene, name in CELLS:
        shape = get_shape(name)
        base, fitted = Tally(), Tally()
        right_net = right_fit = 0
        for seed in range(n):
            s = make_sample(name, SCENES[scene], 256, 5000 + seed, LIB)
            truth_r = shape.ratio_vector(s.ratios)
            nets = network_corners(fitter, s.noisy)
            net_ms = sum(v[4] for v in nets.values())
            t0 = time.perf_counter()
            fits = {k: cuboid.fit_mask(s.noisy, get_shape(k), v[0], v[1], get_shape(k).ratio_vector(v[2]),
                                     weights=cuboid.MaskFitWeights(ratios=RATIO_WEIGHT))
                    for k, v in nets.items()}
            fit_ms = 1e3 * (time.perf_counter() - t0)
            kp, _, ratios, _, _ = nets[name]
            base.add(kp, s.keypoints, get_shape(name).ratio_vector(ratios), truth_r, net_ms)
            fitted.add(fits[name].keypoints, s.keypoints, fits[name].camera.ratios(), truth_r, net_ms + fit_ms)
            right_net += ("twobox" if nets["twobox"][3] > nets["box"][3] + RICHER_SHAPE_MARGIN else "box") == name
            right_fit += cuboid.select(fits) == name
        print(f"| {scene} | {name} | networks only | {n} | {base.row()} | shape right {right_net / n:.0%} |")
        print(f"| {scene} | {name} | networks + mask fit | {n} | {fitted.row()} | shape right {right_fit / n:.0%} |",
              flush=True)


if __name__ == "__main__":
    from cuboidgen.occluders.library import OccluderLibrary
    LIB = OccluderLibrary.load(None)
    {"exact": exact, "networks": networks}[sys.argv[1]](int(sys.argv[2]))
