"""The GPU campaign (issue 40) on the CPU: a lease end to end, applying it, two leases against one, the state's sizes."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from cuboidtrain.campaign import lease as lease_module
from cuboidtrain.campaign import plan as plan_module
from cuboidtrain.campaign import state as state_module
from cuboidtrain.campaign import training as training_module
from cuboidtrain.campaign.apply import apply_lease
from cuboidtrain.campaign.lease import LeaseOptions, run_lease
from cuboidtrain.campaign.plan import CampaignPlan, PhasePlan, load_plan, save_plan
from cuboidtrain.campaign.smoke import SmokeFailed, smoke_check
from cuboidtrain.campaign.state import read_log, read_state, restore, store
from cuboidtrain.models.checkpoint import load_checkpoint, save_checkpoint
from cuboidtrain.models.networks import build_model
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.train.loop import run
from shared.errors import UsageError
from shared.sample import encode
from shared.spool import SpoolWriter
from tests.conftest import ARCH, build_sample, command_here, train_config

ROOT = Path(__file__).resolve().parents[1]
SIZE = 32
MB = 1_000_000
# The tiny campaign: one shape, a few steps a phase, one generator of one worker, one mask a set (the
# lease's row needs each set's figure for both models, not its spread).
TINY = CampaignPlan(arch=ARCH, size=SIZE, shapes=("box",), batch_size=4,
                    phases=(PhasePlan("1", 4, 2e-3), PhasePlan("2", 3, 1e-3)), sigma=None, scenes=("paper",),
                    spool_limit=200, generator_size=64, loader_workers=0, generator_workers=1, eval_samples=1,
                    eval_minutes=0.75)


def new_campaign(folder: Path, plan: CampaignPlan = TINY) -> Path:
    save_plan(folder, plan)
    return folder


def lease(campaign: Path, out: Path, **changes) -> dict:
    options = LeaseOptions(out=out, campaign=campaign, work=out.parent / f"{out.name}-work", minutes=2.0, device="cpu",
                           commit="test", threads=1, eval_threads=1)
    return run_lease(replace(options, **changes))


@pytest.fixture(scope="module")
def first_lease(tmp_path_factory) -> tuple[Path, Path, dict]:
    """One lease of the tiny campaign as the lent machine runs it (recipes/campaign.sh): generators,
    training, evaluation."""
    root = tmp_path_factory.mktemp("campaign")
    campaign, out = new_campaign(root / "campaign"), root / "out"
    # MINUTES is a deadline, not a duration (--lease-steps ends the training): 4, not 2, so that on a busy
    # machine the evaluation is not cut off at it (seen at 2: the row then lacks the shipped models' figures)
    # WHEELS: not the checkout's .whl/, which after a real lease holds the lent machine's cp312 wheels (seen: pip
    # refused them here and the lease failed before it began)
    env = os.environ | {"OUT": str(out), "PY": sys.executable, "DEVICE": "cpu", "CAMPAIGN": str(campaign), "MINUTES": "4",
                        "WORK": str(root / "work"), "COMMIT": "test", "WHEELS": str(root / "no-wheels")}
    done = subprocess.run([str(ROOT / "recipes" / "campaign.sh"), "--lease-steps", "2", "--threads", "1",
                           "--eval-threads", "1"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    return campaign, out, json.loads((out / "lease.json").read_text())["row"]


def test_a_lease_runs_end_to_end_and_returns_state_row_and_evaluation(first_lease):
    campaign, out, row = first_lease
    returned = sorted(p.name for p in out.iterdir())
    assert returned == ["box.state.00", "eval.json", "lease.json", "lease.log"]
    assert all(p.stat().st_size <= 16 * MB for p in out.iterdir())  # what the device sends back
    assert row["lease"] == 1 and row["base"] == "none" and row["commit"] == "test" and row["device"].startswith("cpu")
    assert row["steps"] == 2 and row["shapes"]["box"]["to"] == ["1", 2] and row["shapes"]["box"]["failed"] is None
    assert row["samples_per_s"] > 0 and 0 <= row["data_wait"] <= 1 and row["minutes_trained"] > 0
    assert row["shapes"]["box"]["samples_seen"] == 2 * TINY.batch_size
    # the campaign's model and the shipped one on the same three sets of bench_accuracy's masks
    assert set(row["eval"]["sets"]) == {"paper-clean/box", "paper/box", "street/box"}
    assert all(set(f) == {"campaign", "shipped"} for f in row["eval"]["sets"].values())
    assert json.dumps(row) in (out / "lease.log").read_text()  # the row, one line, in the lease's log too
    assert read_log(campaign) == [] and read_state(campaign) == {}  # the lease changed nothing in the repository


def test_apply_takes_a_lease_into_the_campaign_once(first_lease, tmp_path):
    campaign, out, row = first_lease
    copy = shutil.copytree(campaign, tmp_path / "campaign")
    apply_lease(out.parent, copy)  # the folder above OUT, as the device's files_at may be
    assert read_log(copy) == [row]
    entry = read_state(copy)["box"]
    assert (entry.phase, entry.step, entry.moments) == ("1", 2, "float32")
    assert load_checkpoint(restore(copy, entry, tmp_path / "last.pt"))["step"] == 2
    assert (copy / "eval-shipped.json").is_file()  # later leases need not score the shipped models again
    newest = json.loads((copy / "eval.json").read_text())  # the lease's own evaluation, as the newest
    assert (newest["lease"], newest["steps"], newest["compare"]) == (1, {"box": ["1", 2]}, row["eval"])
    assert newest["campaign"] == json.loads((out / "eval.json").read_text())["campaign"]
    with pytest.raises(UsageError, match="already applied"):
        apply_lease(out, copy)
    assert read_log(copy) == [row]


def test_apply_refuses_a_damaged_part_and_changes_nothing(first_lease, tmp_path):
    campaign, out, _ = first_lease
    damaged = shutil.copytree(out, tmp_path / "out")
    part = damaged / "box.state.00"
    data = bytearray(part.read_bytes())
    data[len(data) // 2] ^= 1
    part.write_bytes(bytes(data))
    copy = shutil.copytree(campaign, tmp_path / "campaign")
    with pytest.raises(UsageError, match="SHA-256 differs"):
        apply_lease(damaged, copy)
    assert sorted(p.name for p in copy.iterdir()) == ["plan.json"]



def test_campaign_evaluate_scores_the_applied_state_here_and_reads_a_kept_nan_as_null(first_lease, tmp_path, monkeypatch):
    """A lease whose own evaluation did not finish is scored here once applied (campaign/eval.json); the
    shipped models' kept figures are read through finite(): an eval-shipped.json an older writer left with
    NaN (as the first H200 lease met it, which then wrote no eval.json) gives null, not a crash. bench_accuracy
    itself ran in the lease above: here its figures for the same weights stand in for a second run."""
    campaign, out, _ = first_lease
    copy = shutil.copytree(campaign, tmp_path / "campaign")
    apply_lease(out, copy)
    kept = json.loads((copy / "eval-shipped.json").read_text())
    kept["rows"][0]["within_1sd"] = float("nan")
    (copy / "eval-shipped.json").write_text(json.dumps(kept))  # Python's json writes the NaN token
    benched = []
    def bench(models, samples, spools, threads, timeout_s, path):
        benched.append({shape: load_checkpoint(file)["step"] for shape, file in models.items()})
        return json.loads((out / "eval.json").read_text())["campaign"]
    monkeypatch.setattr(lease_module, "bench", bench)
    record = lease_module.evaluate_state(copy, tmp_path / "work", threads=1)
    assert benched == [{"box": 2}]  # the applied state's model, packed; the shipped ones' figures kept, not rerun
    assert json.loads((copy / "eval.json").read_text()) == record
    assert record["lease"] == 1 and record["steps"] == {"box": ["1", 2]}
    assert set(record["compare"]["sets"]) == {"paper-clean/box", "paper/box", "street/box"}
    assert all(set(f) == {"campaign", "shipped"} for f in record["compare"]["sets"].values())
    assert record["shipped"]["rows"][0]["within_1sd"] is None and record["shipped_from"] == "eval-shipped.json"
    with pytest.raises(UsageError, match="no state yet"):
        lease_module.evaluate_state(campaign, tmp_path / "work2", threads=1)


def test_an_evaluation_that_fails_keeps_the_lease_and_says_why(frozen_spool, tmp_path, monkeypatch):
    monkeypatch.setattr(lease_module, "smoke_check", lambda plan, device: "cpu (smoke check left out)")
    monkeypatch.setattr(training_module, "subprocess", SimpleNamespace(Popen=TrainerHere, STDOUT=subprocess.STDOUT))
    def broken(*args, **kwargs):
        raise ValueError("eval.json: shipped.rows[0].within_1sd is nan")
    monkeypatch.setattr(lease_module, "evaluate", broken)
    campaign = new_campaign(tmp_path / "campaign")
    row = lease(campaign, tmp_path / "a", lease_steps=1, spool=frozen_spool)
    assert row["eval"] == {"failed": "ValueError: eval.json: shipped.rows[0].within_1sd is nan"}
    assert json.loads((tmp_path / "a" / "lease.json").read_text())["row"] == row
    assert apply_lease(tmp_path / "a", campaign)["shapes"]["box"]["to"] == ["1", 1]  # the training was kept


class TrainerHere:
    """A lease's trainer command (`python -m cuboidtrain run ...`, cuboidtrain.campaign.training) run to its
    end in this process, its output into the log the lease gave it, then read as a finished process."""

    def __init__(self, command: list[str], stdout, stderr=None):
        assert command[1:3] == ["-m", "cuboidtrain"], command
        done = command_here(command[3:])
        with stdout:
            stdout.write(done.stdout + done.stderr)
        self.returncode = done.returncode

    def poll(self) -> int:
        return self.returncode


@pytest.fixture(scope="module")
def frozen_spool(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("frozen")
    with SpoolWriter(path, limit=0) as writer:
        for seed in range(12):  # 3 batches an epoch: leases stop mid-epoch
            writer.publish(encode(build_sample(seed, "box", size=SIZE)))
    return path


def test_two_leases_train_as_the_trainer_uninterrupted(frozen_spool, tmp_path, monkeypatch):
    """Lease A trains phase 1 to step 3; lease B resumes it to its end (step 4) and phase 2 to step 2.
    The trainer run straight through, phase 1 to step 4 then phase 2 to step 2 from its weights, ends
    with the same weights bit for bit and the same losses on the way: the step counter, the cosine's
    position, the optimizer, the data order and the RNG all continued across the leases."""
    # The smoke check (a fresh interpreter importing torch, one step) ran in the end-to-end lease; here
    # it would only repeat itself twice: what these leases show is the run continuing across them.
    monkeypatch.setattr(lease_module, "smoke_check", lambda plan, device: "cpu (smoke check left out)")
    # Each trainer in this process, too: the end-to-end lease ran them as processes, and a fresh one spends
    # seconds importing torch before its three steps.
    monkeypatch.setattr(training_module, "subprocess", SimpleNamespace(Popen=TrainerHere, STDOUT=subprocess.STDOUT))
    campaign = new_campaign(tmp_path / "campaign")
    first = lease(campaign, tmp_path / "a", lease_steps=3, spool=frozen_spool, evaluate=False)
    apply_lease(tmp_path / "a", campaign)
    second = lease(campaign, tmp_path / "b", lease_steps=3, spool=frozen_spool, evaluate=False)
    apply_lease(tmp_path / "b", campaign)
    assert (first["shapes"]["box"]["to"], second["shapes"]["box"]["from"], second["shapes"]["box"]["to"]) == \
           (["1", 3], ["1", 3], ["2", 2])
    assert [r["lease"] for r in read_log(campaign)] == [1, 2]
    # the same phases as the lease's trainer runs them (cuboidtrain.campaign.training.trainer_command), uninterrupted
    p1, p2 = TINY.phases
    common = dict(spool=str(frozen_spool), shape="box", size=SIZE, arch=ARCH, batch_size=TINY.batch_size,
                  lr_schedule="cosine", loader_workers=0, seed=TINY.seed, log_every=1, checkpoint_every=500,
                  device="cpu", dashboard=False, max_wait=120)
    run(TrainConfig(phase="1", steps=p1.steps, lr=p1.lr, out=str(tmp_path / "p1"), **common).validate())
    run(TrainConfig(phase="2", steps=p2.steps, stop_at=2, lr=p2.lr, init=str(tmp_path / "p1" / "last.pt"),
                    out=str(tmp_path / "p2"), **common).validate())
    leased = load_checkpoint(restore(campaign, read_state(campaign)["box"], tmp_path / "leased.pt"))
    straight = load_checkpoint(tmp_path / "p2" / "last.pt")
    assert leased["step"] == straight["step"] == 2 and leased["loader"] == straight["loader"]
    for key, value in straight["model"].items():
        assert torch.equal(value, leased["model"][key]), key
    def totals(folder: Path) -> list[float]:
        return [json.loads(line)["total"] for line in (folder / "metrics.jsonl").read_text().splitlines()]
    assert totals(tmp_path / "b-work/box/p2") == totals(tmp_path / "p2") and len(totals(tmp_path / "p2")) == 2
    assert totals(tmp_path / "b-work/box/p1") == totals(tmp_path / "p1")[3:]  # phase 1's last step, in lease B


def checkpoint_of(tmp_path: Path, arch: str, shape: str, size: int, steps: int = 1) -> Path:
    """A trainer's checkpoint with Adam's moments filled (one step on random weights' own gradients)."""
    model = build_model(shape, size, arch=arch)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    for _ in range(steps):
        sum(p.square().sum() for p in model.parameters()).backward()
        optimizer.step()
    config = train_config(shape=shape, size=size)
    return save_checkpoint(tmp_path / f"{shape}-{arch}.pt", model, config, 7, optimizer)


def test_a_state_over_budget_keeps_adams_moments_in_bfloat16_and_in_parts_that_resume(tmp_path, monkeypatch):
    plan = replace(TINY, shapes=("box", "twobox"))
    checkpoints = {s: checkpoint_of(tmp_path, ARCH, s, SIZE) for s in plan.shapes}
    exact = sum(p.stat().st_size for p in checkpoints.values())
    monkeypatch.setattr(state_module, "STATE_BYTES", exact - 1)
    monkeypatch.setattr(state_module, "PART_BYTES", 100_000)
    (tmp_path / "state").mkdir()
    entries = store(checkpoints, plan, tmp_path / "state")
    for shape, entry in entries.items():
        assert entry.moments == "bfloat16" and len(entry.parts) > 1
        assert all((tmp_path / "state" / p).stat().st_size <= 100_000 for p in entry.parts)
        restored = load_checkpoint(restore(tmp_path / "state", entry, tmp_path / f"{shape}.pt"))
        original = load_checkpoint(checkpoints[shape])
        for key, value in original["model"].items():
            assert torch.equal(value, restored["model"][key]), key  # the weights stay exact
        model = build_model(shape, SIZE, arch=ARCH)
        optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
        optimizer.load_state_dict(restored["optimizer"])  # torch casts the moments back to float32
        moments = next(iter(optimizer.state.values()))
        assert moments["exp_avg_sq"].dtype == torch.float32
    monkeypatch.setattr(state_module, "STATE_BYTES", exact)
    assert all(e.moments == "float32" for e in store(checkpoints, plan, tmp_path / "state").values())


def test_the_committed_campaign_fits_its_budget():
    """campaign/ holds at most 48 MB and no file over 16 MB; the plan's state, exact or with its moments
    halved, fits the budget in parts the device can return (weights, two moments: 12 or 8 bytes a parameter)."""
    folder = ROOT / "campaign"
    sizes = {p.name: p.stat().st_size for p in folder.iterdir() if p.is_file()}
    assert sum(sizes.values()) <= 48 * MB and max(sizes.values()) <= 16 * MB, sizes
    plan = load_plan(folder)
    params = sum(sum(p.numel() for p in build_model(s, plan.size, arch=plan.arch).parameters()) for s in plan.shapes)
    assert min(12, 8 if 12 * params > plan_module.STATE_BYTES else 12) * params <= plan_module.STATE_BYTES
    assert plan_module.PART_BYTES <= 16 * MB
    parts = sum(-(-12 * params // len(plan.shapes) // plan_module.PART_BYTES) for _ in plan.shapes)
    assert parts + 3 <= 8  # the parts, lease.json, eval.json and lease.log: what one run call returns


def test_the_smoke_check_fails_in_one_line_without_cuda():
    if torch.cuda.is_available():
        pytest.skip("CUDA is visible here")
    with pytest.raises(SmokeFailed, match=r"^smoke check: CUDA is not visible .*; nothing trained"):
        smoke_check(TINY, "cuda")


def test_a_plan_with_an_unknown_key_or_phase_is_refused(tmp_path):
    save_plan(tmp_path, TINY)
    data = json.loads((tmp_path / "plan.json").read_text())
    (tmp_path / "plan.json").write_text(json.dumps(data | {"archs": "slim"}))
    with pytest.raises(UsageError, match=r"unknown keys \['archs'\]"):
        load_plan(tmp_path)
    (tmp_path / "plan.json").write_text(json.dumps(data | {"phases": [{"phase": "2", "steps": 1, "lr": 1e-3},
                                                                      {"phase": "1", "steps": 1, "lr": 1e-3}]}))
    with pytest.raises(UsageError, match="phases"):
        load_plan(tmp_path)


def test_a_lease_without_evaluation_trains_until_the_state_must_be_packed(frozen_spool, tmp_path, monkeypatch):
    """Leases 3-5 ran --no-evaluate and still stopped the plan's eval_minutes before their deadline."""
    monkeypatch.setattr(lease_module, "smoke_check", lambda plan, device: "cpu (smoke check left out)")
    monkeypatch.setattr(training_module, "subprocess", SimpleNamespace(Popen=TrainerHere, STDOUT=subprocess.STDOUT))
    ends = []
    real = lease_module.train_until
    def train_until(plan, courses, spools, device, deadline, *args, **kwargs):
        ends.append(deadline - time.monotonic())
        return real(plan, courses, spools, device, deadline, *args, **kwargs)
    monkeypatch.setattr(lease_module, "train_until", train_until)
    campaign = new_campaign(tmp_path / "campaign")
    lease(campaign, tmp_path / "a", lease_steps=1, spool=frozen_spool, evaluate=False, minutes=2.0)
    lease(campaign, tmp_path / "b", lease_steps=1, spool=frozen_spool, evaluate=True, minutes=2.0)
    # seconds of the 120 left to train, measured a moment after the lease began
    assert 120 - lease_module.STORE_MINUTES * 60 - 10 < ends[0] <= 120 - lease_module.STORE_MINUTES * 60
    assert ends[1] <= 120 - TINY.eval_minutes * 60 < ends[0] - 20
