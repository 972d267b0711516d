"""The campaign's plan (campaign/plan.json): what the standing run trains, in which phases, to which step.

The plan is written by hand and committed; a lease reads it and never changes it. Each phase's
cosine runs over its `steps`, counted across leases (the trainer's --steps, with --stop-at or
--max-minutes ending a lease's share), so a lease continues the schedule where the last one left
it. Changing a phase's `steps` mid-campaign moves the rest of its cosine: say so in the log.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from shared.errors import UsageError
from shared.shapes import SHAPES
from shared.files import write_json

PLAN = "plan.json"
# What comes back from a lease (the device tool): at most 8 files of 16 MiB; the state folder holds
# at most 48 MB, no file over 16 MB. A part of 15,000,000 bytes is under both units.
PART_BYTES = 15_000_000
STATE_BYTES = 44_000_000  # every shape's state together: 48 MB less room for the log and the plan


@dataclass(frozen=True)
class PhasePlan:
    """One of the paper's phases (cuboidtrain run --phase), trained until `steps` at peak rate `lr`."""

    phase: str  # "1" or "2": each network alone, then chained
    steps: int  # the cosine's end, counted across leases
    lr: float  # its peak rate (cosine down to lr/100 at `steps`)


@dataclass(frozen=True)
class CampaignPlan:
    arch: str = "compact"  # at 128 px: chosen on the CPU (benchmarks/gpu/choose_campaign_model.py, BENCHMARKS.md)
    size: int = 128  # px
    shapes: tuple[str, ...] = ("box", "twobox")  # one standing run each, side by side on the one GPU
    batch_size: int = 256
    phases: tuple[PhasePlan, ...] = (PhasePlan("1", 12000, 1.5e-3), PhasePlan("2", 8000, 3e-4))
    sigma: float | None = 3.0  # px, heat-map std (None: the trainer's size/128)
    scenes: tuple[str, ...] = ("paper", "street")  # one generator each, per shape
    spool_limit: int = 20000  # samples a spool keeps (cuboidgen run --limit)
    generator_size: int = 256  # px, the spool's samples (the trainer reframes them to `size`)
    loader_workers: int = 3  # a trainer's (BENCHMARKS.md, "On one H100": data wait 5.4-6.5% at 3)
    generator_workers: int | None = None  # each generator's; None: the cores the trainers leave
    seed: int = 0  # the weights' and the epoch order's (cuboidtrain run --seed)
    eval_samples: int = 20  # masks a set and shape for each lease's evaluation (bench_accuracy's sets)
    # Kept at the end of a lease for stopping, packing and evaluating the campaign's models (the shipped
    # ones' figures are kept in campaign/eval-shipped.json): 30 masks a set took 69 s on the 2-core VM
    # for the 64 px models once the spools were drawn; compact 128 px fits 2.2x slower (slim 1.6x), so 20
    # masks fit on a core as fast as the VM's only if the lent machine's is faster: the first lease's log says.
    eval_minutes: float = 1.25
    notes: str = ""

    def validate(self) -> "CampaignPlan":
        if not self.shapes or any(s not in SHAPES for s in self.shapes) or len(set(self.shapes)) != len(self.shapes):
            raise UsageError(f"plan: shapes {list(self.shapes)}: expected some of {', '.join(SHAPES)}, each once")
        if not self.phases or [p.phase for p in self.phases] not in (["1"], ["2"], ["1", "2"]):
            raise UsageError(f"plan: phases {[p.phase for p in self.phases]}: expected ['1', '2'], ['1'] or ['2']")
        if any(p.steps < 1 or not 0 < p.lr <= 1 for p in self.phases):
            raise UsageError("plan: each phase needs steps >= 1 and 0 < lr <= 1")
        return self

    def phase_after(self, phase: str) -> PhasePlan | None:
        names = [p.phase for p in self.phases]
        return self.phases[names.index(phase) + 1] if names.index(phase) + 1 < len(names) else None

    def phase(self, name: str) -> PhasePlan:
        for p in self.phases:
            if p.phase == name:
                return p
        raise UsageError(f"plan: no phase {name!r} (phases {[p.phase for p in self.phases]})")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "CampaignPlan":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise UsageError(f"plan: unknown keys {unknown}; expected some of {sorted(known)}")
        values = dict(data)
        if "phases" in values:
            values["phases"] = tuple(PhasePlan(str(p["phase"]), int(p["steps"]), float(p["lr"])) for p in values["phases"])
        for key in ("shapes", "scenes"):
            if key in values:
                values[key] = tuple(values[key])
        return cls(**values).validate()


def load_plan(campaign: Path) -> CampaignPlan:
    path = Path(campaign) / PLAN
    try:
        return CampaignPlan.from_dict(json.loads(path.read_text()))
    except FileNotFoundError:
        raise UsageError(f"{path}: no such file: a campaign folder holds its plan") from None
    except (ValueError, TypeError, KeyError) as exc:
        raise UsageError(f"{path}: not a campaign plan ({exc})") from None


def save_plan(campaign: Path, plan: CampaignPlan) -> Path:
    path = Path(campaign) / PLAN
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, plan.to_dict(), indent=2)
    return path
