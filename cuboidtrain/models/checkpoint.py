"""Checkpoints: one torch file with explicit keys, a format and a version, written atomically.

A checkpoint records the shape class, size, heat-map sigma and the whole
TrainConfig beside the weights; for `--resume` also the optimizer, the step,
the loader's position and every RNG, so the next step is the one that would
have run. Writing goes to a temporary file in the same folder, then
`os.replace`: a reader (or a crash) sees the old file or the new one, never half.
A write that fails (a full disk) raises the OSError itself, with the temporary file
closed and removed: the old checkpoint stays, and so does the disk's free space.

torch.save's zip archive holds a CRC-32 of every record, but torch.load never checks them: a
flipped bit in a tensor loads as a changed weight (28 of 30 random flips in the shipped box
model did, silently). So every load checks them first (`check_intact`, zipfile's own reading:
about 5 ms for a 4 MB model), and a damaged file is refused naming itself (`DamagedFile`).
"""
from __future__ import annotations

import errno
import os
import random
import zipfile
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from cuboidtrain.models.networks import CuboidNet
from cuboidtrain.models.pdm import PointDistributionModel
from shared.errors import UsageError
from shared.files import atomic_path, temporary_name

FORMAT = "cuboid-fit/checkpoint"  # a training run's state: weights, optimizer, loader, RNG (cuboidtrain run)
MODEL_FORMAT = "cuboid-fit/model"  # weights, config and model card only (cuboidtrain.models.zoo.pack)
VERSION = 1


class DamagedFile(UsageError):
    """A checkpoint or model file whose bytes are not those written: a record's CRC-32 does not
    match, or the archive no longer reads (a flipped bit, a torn copy)."""


class RunConfig(Protocol):
    """What a checkpoint keeps of a training run's config (`cuboidtrain.train.config.TrainConfig`):
    the models' layer knows this much of the trainer, and imports nothing of it."""

    heatmap_sigma: float

    def resolved(self) -> "RunConfig": ...

    def to_dict(self) -> dict: ...


def rng_state() -> dict:
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def non_finite_weights(state: dict) -> tuple[int, int]:
    """(weights that are NaN or Infinity, weights in all) of a state dict's floating-point tensors."""
    bad = total = 0
    for tensor in state.values():
        if torch.is_tensor(tensor) and tensor.is_floating_point():
            bad += int((~torch.isfinite(tensor)).sum())
            total += tensor.numel()
    return bad, total


def save_checkpoint(path: str | Path, model: CuboidNet, config: RunConfig, step: int,
                    optimizer: torch.optim.Optimizer | None = None, loader: object | None = None,
                    metrics: dict | None = None, previous: Path | None = None) -> Path:
    """`loader`: the data loader's position (`cuboidtrain.data.sampler.LoaderState`, kept as its fields).
    `previous`: where the checkpoint `path` held until now is kept (a hard link: no copy), for a
    resume whose newest checkpoint turns out damaged. Raises ValueError, writing nothing, for
    weights that are NaN or Infinity: a diverged model never replaces the last good checkpoint."""
    path = Path(path)
    bad, total = non_finite_weights(model.state_dict())
    if bad:
        raise ValueError(f"checkpoint {path}: not written at step {step}: {bad} of {total} weights are NaN or Infinity")
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "shape": model.shape,
        "size": model.size,
        "arch": model.arch,
        "sigma": config.heatmap_sigma,
        "config": config.resolved().to_dict(),
        "step": step,
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "loader": vars(loader) if loader is not None else None,
        "rng": rng_state(),
        "metrics": metrics or {},
    }
    with atomic_path(path) as tmp:
        _save(payload, tmp)
        if previous is not None and path.is_file():
            keep_previous(path, previous)
    return path


def keep_previous(path: Path, previous: Path) -> None:
    """`previous` becomes the file `path` is now (a hard link, atomically replaced), before `path`
    is replaced: a reader sees a whole older checkpoint there, or the one before it."""
    tmp = previous.with_name(temporary_name(previous.name))  # the run folder's orphan sweep knows the name
    try:
        os.link(path, tmp)
        os.replace(tmp, previous)
    except OSError:  # a file system without hard links: no previous checkpoint, as before
        tmp.unlink(missing_ok=True)


class _Sink:
    """torch.save's destination: a file descriptor, each buffer written whole.

    Given a path, torch.save writes through its own C++ file and turns a full disk into a bare
    RuntimeError ("[enforce fail at inline_container.cc] unexpected pos ..."), and that file stays
    open while the exception lives. Through a sink the OSError is kept (`error`), and the file is
    ours to close. A write after `close` (torch's writer finishing late) touches no descriptor."""

    def __init__(self, fd: int):
        self.fd: int | None = fd
        self.error: OSError | None = None

    def write(self, data) -> int:
        if self.fd is None:
            raise OSError(errno.EBADF, "checkpoint file already closed")
        view = memoryview(data).cast("B")
        try:
            while view:
                view = view[os.write(self.fd, view):]
        except OSError as exc:
            self.error = exc
            raise
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self.fd is not None:
            fd, self.fd = self.fd, None
            os.close(fd)


def _save(payload: dict, path: Path) -> None:
    """torch.save to `path`, synced; a failed write raises its OSError, the file closed."""
    sink = _Sink(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644))
    try:
        try:
            torch.save(payload, sink)
        except Exception:  # torch's wrapping of the sink's error (RuntimeError in torch 2.x)
            if sink.error is not None:
                raise sink.error from None
            raise
        os.fsync(sink.fd)  # a filesystem that allocates late says ENOSPC here, not at the write
    finally:
        sink.close()


def check_intact(path: Path) -> None:
    """Raises DamagedFile unless every record of torch.save's zip archive at `path` reads back
    with the CRC-32 it was written with (a file of another kind is left to torch.load to refuse)."""
    with open(path, "rb") as f:
        if f.read(4) != b"PK\x03\x04":  # no zip (a foreign file, a pre-1.6 pickle): torch.load refuses or reads it
            return
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as exc:
        raise DamagedFile(f"checkpoint {path}: damaged: the archive does not read ({exc}): a torn copy or "
                          f"a flipped bit; not loaded") from None
    if bad is not None:
        raise DamagedFile(f"checkpoint {path}: damaged: {bad} does not have the CRC-32 it was written with "
                          f"(a flipped bit or a torn copy); not loaded")


def read_torch_file(path: Path, what: str, weights_only: bool) -> object:
    """What torch.save wrote to `path`, its bytes checked first (`check_intact`); a one-line UsageError
    naming `what` it should be for a missing, damaged, truncated or foreign file."""
    if not path.is_file():
        raise UsageError(f"{what} {path}: no such file")
    check_intact(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=weights_only)
    except Exception as exc:  # torch raises many types for a truncated or foreign file
        if not _torch_file(path):  # a PNG, a text file: say what it is not, not what pickle tripped on
            raise UsageError(f"{what} {path}: cannot read it: not a cuboid-fit {what} "
                             f"(not a file that torch.save writes)") from None
        raise UsageError(f"{what} {path}: cannot read it ({type(exc).__name__}: {exc})") from None


def load_checkpoint(path: str | Path, shape: str | None = None, size: int | None = None,
                    arch: str | None = None) -> dict:
    """The checkpoint's dict, checked (its bytes first: `check_intact`); ValueError names what is wrong with it."""
    path = Path(path)
    # weights_only=False: the payload holds RNG states (numpy arrays, tuples); only load your own files
    return checked_checkpoint(path, read_torch_file(path, "checkpoint", weights_only=False), shape, size, arch)


def checked_checkpoint(path: Path, ckpt: object, shape: str | None = None, size: int | None = None,
                       arch: str | None = None) -> dict:
    """`ckpt`, what `path` holds (`read_torch_file`), checked as `load_checkpoint` checks it."""
    if not isinstance(ckpt, dict) or ckpt.get("format") not in (FORMAT, MODEL_FORMAT):
        raise UsageError(f"checkpoint {path}: not a cuboid-fit checkpoint (expected format {FORMAT!r} "
                         f"or {MODEL_FORMAT!r})")
    if ckpt.get("version") != VERSION:
        raise UsageError(f"checkpoint {path}: format version {ckpt.get('version')!r}, expected {VERSION}")
    bad, total = non_finite_weights(ckpt.get("model") or {})
    if bad:  # written before save_checkpoint refused them: no fit or metric could be finite
        raise UsageError(f"checkpoint {path}: {bad} of {total} weights are NaN or Infinity (a diverged training): "
                         f"not a model to use")
    if shape is not None and ckpt["shape"] != shape:
        raise UsageError(f"checkpoint {path}: a {ckpt['shape']!r} model, expected {shape!r}")
    if size is not None and ckpt["size"] != size:
        raise UsageError(f"checkpoint {path}: a {ckpt['size']} px model, expected {size} px")
    if arch is not None and checkpoint_arch(ckpt) != arch:
        raise UsageError(f"checkpoint {path}: a {checkpoint_arch(ckpt)!r} arch model, expected {arch!r} (--arch)")
    return ckpt


def load_model(path: str | Path, shape: str | None = None, size: int | None = None) -> tuple[CuboidNet, dict]:
    """A model rebuilt from its checkpoint (on the CPU, in eval mode) and the checkpoint dict."""
    ckpt = load_checkpoint(path, shape, size)
    model = CuboidNet(ckpt["shape"], ckpt["size"], ckpt["sigma"], checkpoint_arch(ckpt), checkpoint_grey(ckpt))
    model.load_state_dict(ckpt["model"])
    if ckpt.get("pdm") is not None:
        model.pdm = PointDistributionModel.from_dict(ckpt["pdm"])
    return model.eval(), ckpt


def _torch_file(path: Path) -> bool:
    """Whether the file starts as torch.save's files do: a zip archive, or (before torch 1.6) a pickle."""
    with open(path, "rb") as f:
        head = f.read(4)
    return head.startswith(b"PK\x03\x04") or head[:1] == b"\x80"


def checkpoint_arch(ckpt: dict) -> str:
    """The checkpoint's architecture; files written before the registry hold the paper's."""
    return ckpt.get("arch", "paper")


def checkpoint_grey(ckpt: dict) -> bool:
    """Whether the checkpoint's R was trained on grey inputs (its run's --grey-input); files
    written before the option read binary masks."""
    return bool((ckpt.get("config") or {}).get("grey_input", False))


def load_models(paths: list[Path]) -> list[CuboidNet]:
    """One model per checkpoint, at most one per shape class (the error names both files)."""
    models, seen = [], {}
    for path in paths:
        model, _ = load_model(path)
        if model.shape in seen:
            raise UsageError(f"--checkpoint {path}: a second {model.shape!r} model ({seen[model.shape]} is one "
                             f"already); give at most one checkpoint per shape class")
        seen[model.shape] = path
        models.append(model)
    return models
