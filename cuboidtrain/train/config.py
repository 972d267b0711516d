"""TrainConfig: every option of `cuboidtrain run`, one field each, with units.

The resolved config is stored in every checkpoint (STYLE.md), so a model file
says exactly how it was trained.
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass, fields, replace

from cuboidtrain.models.settings import check_device
from shared.checks import MAX_SEED, check_choice, PER_CORE, check_numbers, max_processes, number
from shared.errors import UsageError
from shared.shapes import get_shape


# Phase 1 and 2 are the paper's scheme (3.3.2); the other two are its ablations (4.1.1).
PHASES = {
    "1": "each network alone on ground-truth inputs (x1->R, x2->S, x3->T)",
    "2": "R, S, T chained, loss aR*D_R + aS*D_S + aT*D_T",
    "e2e": "ablation: R, S, T chained from scratch, final loss D_T only",
    "finetune": "ablation: a trained model fine-tuned chained, final loss D_T only",
}
LR_SCHEDULES = ("constant", "cosine")  # cosine decays to lr/100 at --steps, or at --max-minutes
MAX_SIZE = 2048  # px: a batch of heat maps grows with size squared (2048 px: 16 MiB per map)
MAX_BATCH = 4096  # samples per step
LOADER_WORKERS_MOST = 6  # loader workers a CUDA run starts by default (`TrainConfig.workers_on`)


@dataclass(frozen=True)
class TrainConfig:
    phase: str = "1"
    spool: str = "data_spool"
    shape: str = "box"
    size: int = number(256, lo=32, hi=MAX_SIZE, integer=True, unit="px")  # the model's square input
    arch: str = "compact"  # a name in cuboidtrain.models.networks.ARCHS: paper (three ResNet-18s), compact, tiny
    reframe: bool = True  # frame each sample as `infer` frames a mask (its visible pieces); any spool size
    grey_input: bool = False  # R reads each model pixel's covered share, not a binary mask (needs reframe: a spool's own framing is binary)
    steps: int | None = number(None, lo=1, integer=True, optional=True)  # train until this step (a run's steps count from 0; --resume continues the count)
    stop_at: int | None = number(None, lo=1, integer=True, optional=True)  # stop (with a checkpoint) after this step, the schedule still running to --steps: one share of a longer run (a campaign's lease)
    epochs: int | None = number(None, lo=1, integer=True, optional=True)  # or this many passes over the spool as listed at each epoch's start; neither: until stopped
    batch_size: int = number(32, lo=1, hi=MAX_BATCH, integer=True)
    lr: float = number(1e-3, lo=0, lo_open=True, hi=1)  # Adam
    lr_schedule: str = "constant"  # or "cosine": decays to lr/100 at --steps (or at --max-minutes without --steps)
    max_minutes: float | None = number(None, lo=0, lo_open=True, optional=True)  # stop (with a checkpoint) after this much wall time
    max_wait: float | None = number(None, lo=0, lo_open=True, optional=True)  # s: give up (exit 1) after waiting this long for a usable sample; None: wait on
    weight_decay: float = number(1e-5, lo=0, hi=1)  # Adam's L2 penalty (paper 3.2)
    sigma: float | None = number(None, lo=0, lo_open=True, optional=True)  # heat-map Gaussian std in px; None: size/128, at least 1
    alpha_r: float = number(1.0, lo=0)  # phase 2 weights of eq. (1)
    alpha_s: float = number(1.0, lo=0)
    alpha_t: float = number(1.0, lo=0)
    ratio_weight: float = number(1.0, lo=0)  # weight of the ratio term inside D_T
    init: str | None = None  # checkpoint whose weights start this run (phase 2, finetune)
    out: str = "runs/p1"
    resume: bool = False  # continue OUT/last.pt exactly
    overwrite: bool = False  # start over in an OUT that holds a run (its last.pt, metrics.jsonl); else refused
    checkpoint_every: int = number(500, lo=1, integer=True)  # steps
    log_every: int = number(10, lo=1, integer=True)  # steps between metrics.jsonl records
    ledger: bool = False  # OUT/ledger.jsonl: every step's samples, by name and payload checksum (cuboidtrain.train.ledger)
    loader_workers: int | None = number(None, lo=0, hi=max_processes(), integer=True, optional=True, unit=PER_CORE)  # DataLoader processes reading the spool; None: `workers_on`
    seed: int = number(0, lo=0, hi=MAX_SEED, integer=True)
    device: str = "auto"  # auto: cuda when present, else cpu
    threads: int | None = number(None, lo=1, hi=max_processes(), integer=True, optional=True, unit=PER_CORE)  # CPU threads for torch; None: torch's default (all cores)
    amp: bool = True  # mixed precision (CUDA only)
    dashboard: bool = True
    val_spool: str | None = None  # evaluated every val_every steps when set
    val_every: int = number(1000, lo=1, integer=True)
    val_samples: int = number(256, lo=1, integer=True)

    def validate(self) -> "TrainConfig":
        check_choice("--phase", self.phase, PHASES)
        get_shape(self.shape)
        from cuboidtrain.models.networks import check_arch  # networks imports this module

        check_arch(self.arch)
        check_numbers(self)  # every numeric field's declared range: finite, in range, the option named
        if self.size % 32:
            raise UsageError(f"--size {self.size}: expected a multiple of 32 (ResNet-18 halves it 5 times)")
        if self.steps is not None and self.epochs is not None:
            raise UsageError("give --steps or --epochs, not both")
        check_choice("--lr-schedule", self.lr_schedule, LR_SCHEDULES)
        if self.lr_schedule == "cosine" and self.steps is None and self.max_minutes is None:
            raise UsageError("--lr-schedule cosine needs --steps N or --max-minutes M: where it decays to lr/100")
        if self.grey_input and not self.reframe:
            raise UsageError("--grey-input needs --reframe: a grey input is the mask framed onto the model's pixels, "
                             "and --no-reframe reads the spool's binary masks as they are")
        if self.sigma is not None and self.sigma > self.size / 4:
            raise UsageError(f"--sigma {self.sigma}: expected at most a quarter of --size ({self.size / 4:g} px)")
        if self.phase in ("1", "2") and not any(self.loss_weights):
            raise UsageError("--alpha-r, --alpha-s, --alpha-t: all 0, nothing would train; expected one > 0")
        if self.phase == "finetune" and not (self.init or self.resume):
            raise UsageError("--phase finetune needs --init CKPT: the trained model to fine-tune")
        if self.phase == "e2e" and self.init:
            raise UsageError("--phase e2e trains from scratch: drop --init (or use --phase finetune)")
        check_device(self.device)
        return self

    def workers_on(self, device_type: str) -> int:
        """The loader's worker processes: --loader-workers, else 2, or on CUDA a quarter of the
        cores, 2 to LOADER_WORKERS_MOST. A worker only reads, decodes and finds each sample's
        framing (the masks are framed on the device): about 8,000 samples/s of one core at 64 px
        (BENCHMARKS.md, "The input path"), so the rest of the cores are left to the generator."""
        if self.loader_workers is not None:
            return self.loader_workers
        return max(2, min(LOADER_WORKERS_MOST, (os.cpu_count() or 1) // 4)) if device_type == "cuda" else 2

    @property
    def heatmap_sigma(self) -> float:
        # Imported here: the codec is torch's, and the command line reads this module for --help.
        from cuboidtrain.models.codec import default_sigma

        return self.sigma if self.sigma is not None else default_sigma(self.size)

    @property
    def loss_weights(self) -> tuple[float, float, float]:
        """(aR, aS, aT) for this phase: the ablations keep only the final loss."""
        if self.phase in ("e2e", "finetune"):
            return (0.0, 0.0, 1.0)
        return (self.alpha_r, self.alpha_s, self.alpha_t)

    def resolved(self) -> "TrainConfig":
        return replace(self, sigma=self.heatmap_sigma)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "TrainConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})
