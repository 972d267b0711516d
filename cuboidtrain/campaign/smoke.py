"""A lease's first seconds: is the device there, does the project import, does one training step run.

Each failure is one line saying what was found (SmokeFailed), before a generator starts or a
minute of the lease is spent training.
"""
from __future__ import annotations

import subprocess
import sys
import time

import torch

from cuboidtrain.campaign.plan import CampaignPlan
from cuboidtrain.data.prepare import ChainBatch
from cuboidtrain.models.networks import build_model
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.train.loop import train_step
from shared.errors import UsageError
from shared.shapes import get_shape

# Imported by the processes a lease starts (the generators, the trainers, bench_accuracy): checked in
# a fresh interpreter, as they will be, so a missing package (watchdog, say) fails here, not mid-lease.
IMPORTS = "import cuboidgen.cli, cuboidtrain.cli, cuboidtrain.train.loop, cuboidtrain.fit.fitter, cv2, rich"


class SmokeFailed(UsageError):
    """The lease cannot run: nothing was trained and the standing state is unchanged."""


def smoke_check(plan: CampaignPlan, device: str) -> str:
    """The device's name once it trained one step of the plan's model on a synthetic batch; SmokeFailed otherwise."""
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise SmokeFailed(f"smoke check: CUDA is not visible (torch {torch.__version__}, built for CUDA "
                          f"{torch.version.cuda}); nothing trained (--device cpu runs on the CPU)")
    found = subprocess.run([sys.executable, "-c", IMPORTS], capture_output=True, text=True, timeout=120)
    if found.returncode:
        last = (found.stderr.strip().splitlines() or ["no message"])[-1]
        raise SmokeFailed(f"smoke check: the project does not import with {sys.executable} ({last}); nothing trained")
    target = torch.device(device)
    try:
        seconds = one_step(plan, target)
    except Exception as exc:  # noqa: BLE001: any failure of the step is the one line this check exists for
        raise SmokeFailed(f"smoke check: one {plan.arch} {plan.size} px step of {plan.batch_size} on {device} failed "
                          f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); nothing trained") from None
    name = torch.cuda.get_device_name(target) if target.type == "cuda" else "cpu"
    return f"{name} (smoke step {seconds:.2f} s)"


def one_step(plan: CampaignPlan, device: torch.device) -> float:
    """Seconds one phase-2 step takes on a random batch of the plan's size (its memory too)."""
    shape = get_shape(plan.shapes[0])
    config = TrainConfig(phase="2", arch=plan.arch, size=plan.size, batch_size=plan.batch_size, sigma=plan.sigma)
    model = build_model(plan.shapes[0], plan.size, plan.seed, config.heatmap_sigma, plan.arch).to(device)
    if device.type == "cuda":
        model.to(memory_format=torch.channels_last)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    b, s, k = plan.batch_size, plan.size, shape.num_keypoints
    mask = torch.where(torch.rand(b, 1, s, s, device=device) > 0.5, 1.0, -1.0)
    x = ChainBatch(x1=mask, x2=mask.clone(), x3=torch.rand(b, k, s, s, device=device),
                   x4=torch.rand(b, k, 2, device=device) * s, ratios=torch.rand(b, len(shape.ratio_names), device=device))
    start = time.perf_counter()
    losses = train_step(model, optimizer, x, config, device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    if not all(map(lambda v: v == v and abs(v) != float("inf"), losses.values())):
        raise ValueError(f"non-finite losses {losses}")
    return time.perf_counter() - start
