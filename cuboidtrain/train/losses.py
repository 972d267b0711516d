"""The paper's loss terms (3.3.2) and how each training phase wires them to R, S and T.

D_R: L1 between the refined mask and the clean one, mean over pixels.
D_S: squared L2 between predicted and rendered heat maps, summed over a map's
     pixels and averaged over maps. (A per-pixel mean would make the loss ~1e-4
     and let the Estimator settle for all-zero maps.)
D_T: squared L2 distance between predicted and true keypoints in px, averaged
     over keypoints, plus `ratio_weight` times the ratios' mean squared error.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from cuboidtrain.data.prepare import ChainBatch
from cuboidtrain.models.networks import CuboidNet


def refiner_loss(refined: torch.Tensor, clean: torch.Tensor) -> torch.Tensor:
    return F.l1_loss(refined.float(), clean)


def estimator_loss(heatmaps: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return ((heatmaps.float() - target) ** 2).sum(dim=(-2, -1)).mean()


def tabulator_loss(keypoints: torch.Tensor, ratios: torch.Tensor, true_keypoints: torch.Tensor,
                   true_ratios: torch.Tensor, ratio_weight: float) -> torch.Tensor:
    squared_px = ((keypoints - true_keypoints) ** 2).sum(dim=-1).mean()
    return squared_px + ratio_weight * F.mse_loss(ratios, true_ratios)


def phase_losses(model: CuboidNet, x: ChainBatch, phase: str, ratio_weight: float) -> dict[str, torch.Tensor]:
    """D_R, D_S, D_T for one batch, and each stage's outputs.

    Phase 1 feeds every network its ground-truth input (x1 -> R, x2 -> S, x3 -> T):
    three independent problems whose gradients never meet. Every other phase
    runs the chain T(S(R(x1))) (`CuboidNet.forward`, as eval and infer run it);
    which terms count is decided by the weights (`combine`).
    """
    if phase == "1":
        refined = model.refiner(x.x1)
        heatmaps = model.estimator(x.x2)
        keypoints, ratios = model.tabulator(x.x3)
    else:
        out = model(x.x1, refine_steps=1)
        refined, heatmaps, keypoints, ratios = out.refined, out.heatmaps, out.keypoints, out.ratios
    return {
        "D_R": refiner_loss(refined, x.x2),
        "D_S": estimator_loss(heatmaps, x.x3),
        "D_T": tabulator_loss(keypoints, ratios, x.x4, x.ratios, ratio_weight),
        "refined": refined,
        "heatmaps": heatmaps,
        "keypoints": keypoints,
        "ratios": ratios,
    }


def combine(losses: dict[str, torch.Tensor], phase: str, weights: tuple[float, float, float]) -> torch.Tensor:
    """The loss to minimise: the plain sum in phase 1 (separate networks, so a sum is
    separate training), eq. (1) with (aR, aS, aT) otherwise."""
    if phase == "1":
        return losses["D_R"] + losses["D_S"] + losses["D_T"]
    a_r, a_s, a_t = weights
    return a_r * losses["D_R"] + a_s * losses["D_S"] + a_t * losses["D_T"]
