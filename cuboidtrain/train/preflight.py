"""What `cuboidtrain run` checks before any step, so that a run is never lost to what could
have been known at its start (issue 22): every path option, what --out already holds, and the
smallest batch the model can step on.
"""
from __future__ import annotations

from pathlib import Path

import torch

from cuboidtrain.models.networks import CuboidNet
from cuboidtrain.train.config import TrainConfig
from shared.errors import UsageError, check_writable
from shared.spool import SpoolError, check_spool

LAST = "last.pt"  # OUT/last.pt: the run's newest checkpoint
PREVIOUS = "previous.pt"  # OUT/previous.pt: the one before it, for a resume that finds last.pt damaged


def least_batch(model: CuboidNet, device: torch.device) -> int:
    """The fewest samples a training step can take: 1, or 2 when some BatchNorm layer sees a
    1x1 map (the paper arch at 32 px): training-mode BatchNorm needs two values per channel.
    Measured with one forward pass of a one-sample batch, not assumed from the arch."""
    seen = []
    hooks = [m.register_forward_pre_hook(lambda _, args: seen.append(args[0][0, 0].numel()))
             for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    was_training = model.training
    try:
        with torch.no_grad():
            model.eval()(torch.zeros(1, 1, model.size, model.size, device=device), refine_steps=1)
    finally:
        model.train(was_training)
        for hook in hooks:
            hook.remove()
    return 1 if min(seen, default=2) >= 2 else 2


def check_paths(config: TrainConfig) -> None:
    """Every path option, checked before any work (issue 22: a missing --val-spool was found
    at the first validation, its step lost): the spools, --init, --out, and what --out holds."""
    spool = Path(config.spool)
    if not spool.exists():
        raise UsageError(f"--spool {spool}: no such folder (start `cuboidgen run --spool {spool} --size {config.size}` "
                         f"first)")
    for option, folder in (("--spool", config.spool), ("--val-spool", config.val_spool)):
        if folder is not None:
            try:
                check_spool(Path(folder), readable=True)
            except SpoolError as exc:
                raise UsageError(f"{option} {str(exc).removeprefix('spool ')}") from None
    if config.init is not None and not Path(config.init).is_file():
        raise UsageError(f"--init {config.init}: no such file (a checkpoint to start from)")
    check_writable("--out", config.out, folder=True)
    check_run_folder(config)


def check_run_folder(config: TrainConfig) -> None:
    """A run folder holding a run (a checkpoint, metrics records) is continued with --resume or
    started over with --overwrite, never replaced unasked (issue 22: a plain `run` replaced a
    step-30 last.pt with step 3 and emptied metrics.jsonl)."""
    out = Path(config.out)
    if config.resume and config.overwrite:
        raise UsageError("--resume continues the run in --out, --overwrite starts it over: give one of them")
    if config.resume and not (out / LAST).is_file():
        raise UsageError(f"--resume: {out / LAST}: no such file (nothing to continue; a new run goes without --resume)")
    held = [name for name in (LAST, "metrics.jsonl") if _holds(out / name)]
    if held and not (config.resume or config.overwrite):
        raise UsageError(f"--out {out} holds a run ({', '.join(held)}): --resume continues it, --overwrite starts it "
                         f"over, or give another --out")


def _holds(path: Path) -> bool:
    try:
        return path.is_file() and path.stat().st_size > 0
    except OSError:
        return False
