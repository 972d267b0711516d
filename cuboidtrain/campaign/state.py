"""The standing state in campaign/: each shape's training checkpoint in parts, their manifest, the log.

A shape's state is the trainer's own checkpoint (`cuboidtrain run`'s last.pt: weights, Adam's
moments, the step, the loader's position, every RNG), so a lease resumes it with `--resume`
exactly. It is stored in parts of at most PART_BYTES (the device returns files of at most
16 MiB) named in `state.json` with their SHA-256. Where every shape's checkpoint together would
pass STATE_BYTES, Adam's two moments are stored as bfloat16 (half their bytes; torch casts them
back to the weights' float32 on load): the weights stay exact, the moments keep 3 significant
digits, far finer than the noise of the running averages they are. `moments` in the manifest
says which. The log (`log.jsonl`) has one row a lease.
"""
from __future__ import annotations

import hashlib
import io
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from cuboidtrain.campaign.plan import PART_BYTES, STATE_BYTES, CampaignPlan
from shared.errors import UsageError
from shared.files import json_text, write_json

MANIFEST = "state.json"
LOG = "log.jsonl"
VERSION = 1
MOMENTS = ("exp_avg", "exp_avg_sq")


@dataclass(frozen=True)
class ShapeState:
    """One shape's standing run: its phase and step, the samples it has seen in all phases, and its parts."""

    shape: str
    phase: str
    step: int
    samples_seen: int
    parts: tuple[str, ...]
    sha256: str  # of the whole checkpoint, the parts joined
    bytes: int
    moments: str  # "float32" (exact) or "bfloat16"

    @classmethod
    def from_dict(cls, data: dict) -> "ShapeState":
        return cls(**{**data, "parts": tuple(data["parts"])})


def read_state(campaign: Path) -> dict[str, ShapeState]:
    """Each shape's state by name; empty before the first lease (no weights committed yet)."""
    path = Path(campaign) / MANIFEST
    if not path.is_file():
        return {}
    data = json.loads(path.read_text())
    if data.get("version") != VERSION:
        raise UsageError(f"{path}: state version {data.get('version')!r}, expected {VERSION}")
    return {shape: ShapeState.from_dict(entry) for shape, entry in data["shapes"].items()}


def state_digest(campaign: Path) -> str:
    """What a lease started from: the manifest's SHA-256 ('none' before the first). A lease is applied
    only onto the state it resumed, so that no lease is applied twice, nor one over a newer."""
    path = Path(campaign) / MANIFEST
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16] if path.is_file() else "none"


def write_manifest(folder: Path, shapes: dict[str, ShapeState]) -> Path:
    path = Path(folder) / MANIFEST
    write_json(path, {"version": VERSION, "shapes": {s: asdict(e) for s, e in shapes.items()}}, indent=2)
    return path


def restore(campaign: Path, entry: ShapeState, destination: Path) -> Path:
    """The shape's checkpoint joined from its parts into `destination` (a run folder's last.pt),
    its SHA-256 checked: a part missing or changed is refused naming it."""
    data = b"".join(_read_part(Path(campaign) / part) for part in entry.parts)
    if hashlib.sha256(data).hexdigest() != entry.sha256:
        raise UsageError(f"{campaign}/{MANIFEST}: the {entry.shape} parts {', '.join(entry.parts)} do not join into "
                         f"the checkpoint it names (SHA-256 differs): a part was changed or is missing")
    destination.parent.mkdir(parents=True, exist_ok=True)
    destination.write_bytes(data)
    return destination


def _read_part(path: Path) -> bytes:
    if not path.is_file():
        raise UsageError(f"{path}: no such file: a part of the campaign's state is missing")
    return path.read_bytes()


def store(checkpoints: dict[str, Path], plan: CampaignPlan, folder: Path) -> dict[str, ShapeState]:
    """Each shape's checkpoint written into `folder` in parts (`SHAPE.state.NN`); Adam's moments in
    bfloat16 when the shapes' exact checkpoints together pass STATE_BYTES. Returns the manifest's entries."""
    payloads = {shape: torch.load(path, map_location="cpu", weights_only=False) for shape, path in checkpoints.items()}
    exact = {shape: path.read_bytes() for shape, path in checkpoints.items()}
    halve = sum(map(len, exact.values())) > STATE_BYTES
    entries = {}
    for shape, payload in payloads.items():
        data = _with_half_moments(payload) if halve else exact[shape]
        parts = []
        for index, start in enumerate(range(0, len(data), PART_BYTES)):
            parts.append(f"{shape}.state.{index:02d}")
            (Path(folder) / parts[-1]).write_bytes(data[start:start + PART_BYTES])
        entries[shape] = ShapeState(shape, payload["config"]["phase"], int(payload["step"]),
                                    samples_seen(plan, payload["config"]["phase"], int(payload["step"])), tuple(parts),
                                    hashlib.sha256(data).hexdigest(), len(data), "bfloat16" if halve else "float32")
    return entries


def _with_half_moments(payload: dict) -> bytes:
    state = payload["optimizer"]["state"] if payload.get("optimizer") else {}
    for moments in state.values():
        for key in MOMENTS:
            if key in moments:
                moments[key] = moments[key].to(torch.bfloat16)
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    return buffer.getvalue()


def samples_seen(plan: CampaignPlan, phase: str, step: int) -> int:
    """Samples the shape's run has trained on in all phases: the earlier phases' whole, this one's to `step`."""
    names = [p.phase for p in plan.phases]
    earlier = names[:names.index(phase)] if phase in names else []
    return plan.batch_size * (sum(plan.phase(p).steps for p in earlier) + step)


def read_log(campaign: Path) -> list[dict]:
    path = Path(campaign) / LOG
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def append_log(campaign: Path, row: dict) -> Path:
    path = Path(campaign) / LOG
    with open(path, "a") as f:
        f.write(json_text(row, what=str(path)) + "\n")
    return path
