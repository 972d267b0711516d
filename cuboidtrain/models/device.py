"""Which device to run on: `auto` is CUDA when present, else the CPU."""
from __future__ import annotations

import torch

from cuboidtrain.models.settings import check_device
from shared.errors import UsageError


def resolve_device(device: str | torch.device) -> torch.device:
    if isinstance(device, torch.device):
        return device
    name = check_device(device)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise UsageError(f"--device {device}: CUDA is not available on this machine")
    return torch.device(name)
