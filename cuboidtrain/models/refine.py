"""Iterative refinement (paper Figure 7): R re-entered on its own binarised output, K times or until settled."""
from __future__ import annotations

import torch
from torch import nn

from cuboidtrain.models.settings import MAX_REFINE_STEPS

# "auto" distrusts a settled mask this far from the Refiner's first pass. On 300 noisy `paper`
# masks the shipped models' later passes only hurt (box: 10.16 px at one pass, 11.09 at two;
# auto 12.38 at 0.9, 10.43 at 0.99, 10.19 at 0.995; twobox 11.56, 11.89, 11.59, 11.56):
# auto keeps a later pass only when it barely moved the mask.
DRIFT_IOU = 0.995


def binarise(refined: torch.Tensor) -> torch.Tensor:
    """Tanh output -> the +-1 mask the Refiner was trained on (> 0 is object, as everywhere).
    A +-1 mask comes back as it went in, value for value."""
    return torch.where(refined > 0, 1.0, -1.0).to(refined.dtype)


def refine(refiner: nn.Module, mask_pm1: torch.Tensor, steps: int | None,
           max_steps: int = MAX_REFINE_STEPS) -> tuple[torch.Tensor, int, bool]:
    """R^K: (B, 1, S, S) masks in [-1, 1] -> (refined tanh output, passes run, whether every mask converged).

    `steps=K` runs R K times: the first pass on the mask as given (+-1, or grey for a model
    trained on grey inputs), each later one on the sign of the previous output (R was
    trained on masks, not tanh values); K=0 hands the raw mask on. `None`
    ("auto") repeats, per mask, until a pass flips none of its pixels. A mask whose
    Refiner never settles within `max_steps` passes, or settles far from its first
    pass (IoU below DRIFT_IOU: grown into a square, eaten away), is not trusted:
    auto then keeps its first pass (one pass is what R was trained to do). A fixed K
    always counts as converged. Passes run is the most any mask of the batch took.
    """
    if steps is not None:  # a count FitOptions has checked; a Python loop, so a traced graph unrolls it
        refined = mask_pm1
        for step in range(steps):
            refined = refiner(refined if step == 0 else binarise(refined))
        return refined, steps, True
    batch = mask_pm1.shape[0]
    settled_at = torch.zeros(batch, dtype=torch.long)  # 0: not settled yet
    refined, first, result, previous = mask_pm1, None, None, None
    for step in range(1, max_steps + 1):
        refined = refiner(refined if step == 1 else binarise(refined))
        current = refined > 0
        if first is None:
            first, result = refined, refined.clone()
        else:
            settled = (current == previous).flatten(1).all(1) & (settled_at == 0)
            result[settled], settled_at[settled] = refined[settled], step
            if (settled_at > 0).all():
                break
        previous = current
    trusted = (settled_at > 0) & (mask_iou(result, first) >= DRIFT_IOU)
    result[~trusted], settled_at[~trusted] = first[~trusted], 1
    return result, int(settled_at.max()), bool(trusted.all())


def mask_iou(refined: torch.Tensor, clean: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) masks in +-1 (object > 0) -> (B,) IoU; two empty masks agree fully (1)."""
    a, b = (refined > 0).flatten(1), (clean > 0).flatten(1)
    inter, union = (a & b).sum(1).float(), (a | b).sum(1).float()
    return torch.where(union > 0, inter / union.clamp(min=1), torch.ones_like(union))
