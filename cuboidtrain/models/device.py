"""Which device to run on (`auto` is CUDA when present, else the CPU), and on how many CPU threads."""
from __future__ import annotations

import contextlib

import torch

from cuboidtrain.models.settings import check_device
from shared.errors import UsageError
from shared.threads import threads_held


def resolve_device(device: str | torch.device) -> torch.device:
    if isinstance(device, torch.device):
        return device
    name = check_device(device)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise UsageError(f"--device {device}: CUDA is not available on this machine")
    return torch.device(name)


@contextlib.contextmanager
def one_thread(device: torch.device):
    """torch's CPU work on one thread inside, the caller's count restored after. A convolution
    sums in another order on two threads than on one: its outputs differ in the last bits, and
    the cuboid fit, whose valleys are flat, turned that into up to 2.5 px (BENCHMARKS.md, "The
    same answer everywhere"). One thread for every mask gives every machine, worker count and
    thread setting the same numbers. On CUDA, nothing changes."""
    if device.type != "cpu":
        yield
        return
    with threads_held(torch.get_num_threads, torch.set_num_threads):
        yield
