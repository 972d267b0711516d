"""Training: loss wiring per phase, a short run that learns, exact resume, SIGTERM, the schedule."""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from cuboidtrain.cli import app
from cuboidtrain.models.checkpoint import load_checkpoint, load_model
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.data.loader import SpoolBatches
from cuboidtrain.data.prepare import prepare_batch
from cuboidtrain.train.losses import combine, phase_losses
from cuboidtrain.train.loop import learning_rate, run
from cuboidtrain.train.monitor.status import TrainerStatus, read_status
from shared.errors import UsageError
from shared.sample import encode
from shared.spool import SpoolWriter, enumerate_spool
from tests.conftest import ARCH, build_sample, tiny_model, train_config

SIZE = 32
CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def spool(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("spool")
    with SpoolWriter(path, limit=0) as writer:
        for seed in range(12):
            writer.publish(encode(build_sample(seed, "box", size=SIZE)))
    return path


def config(spool: Path, out: Path, **changes) -> TrainConfig:
    base = train_config(spool=str(spool), out=str(out), shape="box", size=SIZE, steps=4, batch_size=4,
                       loader_workers=0, dashboard=False, log_every=1, checkpoint_every=1000)
    return replace(base, **changes).validate()


def batch_of(spool: Path, count: int = 4) -> dict:
    batch = SpoolBatches(spool, "box", SIZE)[enumerate_spool(spool)[:count]]
    return prepare_batch(batch, CPU, 1.0, SIZE)


def grads_by_network(model, loss: torch.Tensor) -> dict[str, bool]:
    model.zero_grad(set_to_none=True)
    loss.backward(retain_graph=True)
    return {
        name: any(p.grad is not None and p.grad.abs().sum() > 0 for p in getattr(model, name).parameters())
        for name in ("refiner", "estimator", "tabulator")
    }


def test_phase_1_trains_each_network_on_its_own_loss(spool):
    model = tiny_model("box", SIZE)
    losses = phase_losses(model, batch_of(spool), "1", ratio_weight=1.0)
    assert grads_by_network(model, losses["D_R"]) == {"refiner": True, "estimator": False, "tabulator": False}
    assert grads_by_network(model, losses["D_S"]) == {"refiner": False, "estimator": True, "tabulator": False}
    assert grads_by_network(model, losses["D_T"]) == {"refiner": False, "estimator": False, "tabulator": True}


def test_phase_2_chains_so_the_final_loss_reaches_every_network(spool):
    model = tiny_model("box", SIZE)
    losses = phase_losses(model, batch_of(spool), "2", ratio_weight=1.0)
    assert grads_by_network(model, losses["D_T"]) == {"refiner": True, "estimator": True, "tabulator": True}
    assert grads_by_network(model, losses["D_S"]) == {"refiner": True, "estimator": True, "tabulator": False}


def test_the_chained_phases_run_the_one_chain_with_the_same_numbers_and_gradients(spool):
    # CuboidNet.forward (the chain infer, eval and export run) must train exactly as R, S and T
    # wired by hand: the sign it takes of the +-1 mask x1 changes no value and no gradient.
    x, model = batch_of(spool), tiny_model("box", SIZE).train()
    by_hand = tiny_model("box", SIZE).train()
    refined = by_hand.refiner(x.x1)
    heatmaps = by_hand.estimator(refined)
    keypoints, ratios = by_hand.tabulator(heatmaps)
    squared_px = ((keypoints - x.x4) ** 2).sum(dim=-1).mean()
    expected = {"D_R": torch.nn.functional.l1_loss(refined, x.x2),
                "D_S": ((heatmaps - x.x3) ** 2).sum(dim=(-2, -1)).mean(),
                "D_T": squared_px + torch.nn.functional.mse_loss(ratios, x.ratios)}
    losses = phase_losses(model, x, "2", ratio_weight=1.0)
    for name in ("D_R", "D_S", "D_T"):
        assert torch.equal(losses[name], expected[name]), name
    combine(losses, "2", (1.0, 1.0, 1.0)).backward()
    combine(expected, "2", (1.0, 1.0, 1.0)).backward()
    for (name, p), q in zip(model.named_parameters(), by_hand.parameters()):
        assert torch.equal(p.grad, q.grad), name


def test_eq_1_weights_and_the_ablations_final_loss_only():
    losses = {"D_R": torch.tensor(1.0), "D_S": torch.tensor(10.0), "D_T": torch.tensor(100.0)}
    assert combine(losses, "2", (1.0, 1.0, 1.0)).item() == 111.0
    assert combine(losses, "2", (0.5, 0.1, 2.0)).item() == 201.5
    for phase in ("e2e", "finetune"):
        cfg = TrainConfig(phase=phase, init="x.pt", steps=1) if phase == "finetune" else TrainConfig(phase=phase, steps=1)
        assert combine(losses, phase, cfg.loss_weights).item() == 100.0


def test_a_short_run_lowers_every_loss_on_its_samples(spool, tmp_path):
    # Train-mode BatchNorm (batch statistics) on both sides: 40 steps are too few for
    # the running statistics that eval mode uses to settle.
    x = batch_of(spool, 8)
    with torch.no_grad():
        before = phase_losses(tiny_model("box", SIZE, seed=0).train(), x, "1", 1.0)
    status = run(config(spool, tmp_path, steps=40, lr=2e-3, batch_size=6))
    with torch.no_grad():
        after = phase_losses(load_model(tmp_path / "last.pt")[0].train(), x, "1", 1.0)
    assert status.state == "done" and status.step == 40
    for key in ("D_R", "D_S", "D_T"):
        assert after[key].item() < 0.7 * before[key].item(), key
    records = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if "D_R" in r] == list(range(1, 41))


def test_resume_reproduces_the_uninterrupted_run(spool, tmp_path):
    # 3 batches per epoch (12 samples, batch 4): stopping at step 2 resumes mid-epoch,
    # and steps 4-6 cross into a freshly shuffled epoch.
    run(config(spool, tmp_path / "straight", steps=6))
    run(config(spool, tmp_path / "split", steps=2))
    run(config(spool, tmp_path / "split", steps=6, resume=True))
    straight = load_checkpoint(tmp_path / "straight" / "last.pt")
    split = load_checkpoint(tmp_path / "split" / "last.pt")
    assert straight["step"] == split["step"] == 6
    assert straight["loader"] == split["loader"]
    for key, value in straight["model"].items():
        assert torch.equal(value, split["model"][key]), key


class Statuses:
    """A dashboard that keeps every status it is shown."""

    def __init__(self):
        self.seen: list[TrainerStatus] = []

    def update(self, status: TrainerStatus) -> None:
        self.seen.append(status)


def test_the_checkpoint_a_resumed_run_continues_is_its_last_until_it_writes_one(spool, tmp_path):
    run(config(spool, tmp_path, steps=2))
    board = Statuses()
    run(config(spool, tmp_path, steps=4, resume=True), dashboard=board)
    before = [s for s in board.seen if s.step < 4 and s.state != "checkpointing"]
    assert before and all(s.last_checkpoint and s.last_checkpoint.step == 2 for s in before)
    assert before[0].last_checkpoint.path == str(tmp_path / "last.pt") and before[0].last_checkpoint.time
    assert board.seen[-1].last_checkpoint.step == 4


def flip_a_bit(path: Path, at: float = 0.5) -> None:
    """One bit flipped at `at` of the file's length (the middle of a zip: a tensor's bytes)."""
    data = bytearray(path.read_bytes())
    data[int(len(data) * at)] ^= 0x04
    path.write_bytes(bytes(data))


def test_a_damaged_last_checkpoint_is_refused_and_resume_falls_back_to_the_previous_one(spool, tmp_path, caplog):
    run(config(spool, tmp_path, steps=4, checkpoint_every=2))  # checkpoints at steps 2 and 4
    assert load_checkpoint(tmp_path / "previous.pt")["step"] == 2 and load_checkpoint(tmp_path / "last.pt")["step"] == 4
    flip_a_bit(tmp_path / "last.pt")
    with pytest.raises(UsageError, match=r"last\.pt: damaged: .* does not have the CRC-32 it was written with"):
        load_checkpoint(tmp_path / "last.pt")
    with caplog.at_level("WARNING"):
        run(config(spool, tmp_path, steps=6, checkpoint_every=2, resume=True))
    assert "resuming from" in caplog.text and "previous.pt (step 2) instead" in caplog.text
    assert load_checkpoint(tmp_path / "last.pt")["step"] == 6 and (tmp_path / "last.pt.damaged").is_file()
    assert load_checkpoint(tmp_path / "previous.pt")["step"] == 4  # the run's own again, not the damaged file
    flip_a_bit(tmp_path / "last.pt")
    flip_a_bit(tmp_path / "previous.pt")
    with pytest.raises(UsageError, match="no previous.pt|previous.pt: damaged"):
        run(config(spool, tmp_path, steps=8, resume=True))


def test_the_ledger_lists_each_step_s_samples_by_name_and_checksum_across_a_resume(spool, tmp_path):
    import msgpack
    import xxhash

    from cuboidtrain.train.ledger import read_ledger

    run(config(spool, tmp_path, steps=2, ledger=True))
    with open(tmp_path / "ledger.jsonl", "a") as torn:
        torn.write('{"step": 3, "rank": 0, "samp')  # a trainer killed mid-line
    run(config(spool, tmp_path, steps=4, ledger=True, resume=True))
    lines = read_ledger(tmp_path / "ledger.jsonl")
    assert [line["step"] for line in lines] == [1, 2, 3, 4] and all(len(line["samples"]) == 4 for line in lines)
    written = {name: msgpack.unpackb((spool / name).read_bytes())["checksum"] for name in enumerate_spool(spool)}
    payloads = {name: xxhash.xxh3_64_intdigest(msgpack.unpackb((spool / name).read_bytes())["payload"]) for name in written}
    for name, checksum in (sample for line in lines for sample in line["samples"]):
        assert checksum == written[name] == payloads[name]
    assert len({name for line in lines for name, _ in line["samples"]}) == 12  # 16 reads of 12 samples: an epoch and more


def test_resume_refuses_another_phase_and_init_another_shape(spool, tmp_path):
    run(config(spool, tmp_path, steps=1))
    with pytest.raises(ValueError, match="phase 1, not 2"):
        run(config(spool, tmp_path, phase="2", steps=2, resume=True))
    with pytest.raises(ValueError, match="'box' model, expected 'twobox'"):
        run(config(spool, tmp_path / "b", shape="twobox", phase="2", init=str(tmp_path / "last.pt")))


def test_a_listing_gone_stale_ends_the_epoch_and_lists_afresh(tmp_path, monkeypatch):
    # A generator that outruns the trainer evicts most of an epoch's listing; the trainer
    # must re-list then, not skip through the dead names one batch at a time.
    spool = tmp_path / "spool"
    with SpoolWriter(spool, limit=0) as writer:
        for seed in range(40):
            writer.publish(encode(build_sample(seed, "box", size=SIZE)))
    import cuboidtrain.train.loop as train_module

    real_prepare, calls = train_module.prepare_batch, []

    def evict_after_first_step(batch, *args):
        if not calls:  # keep 8 samples, as if the generator replaced the rest
            for name in enumerate_spool(spool)[8:]:
                (spool / name).unlink()
        calls.append(1)
        return real_prepare(batch, *args)

    monkeypatch.setattr(train_module, "prepare_batch", evict_after_first_step)
    status = run(config(spool, tmp_path / "run", steps=3))
    assert status.step == 3
    assert 0 < status.skipped["vanished"] <= 8  # one stale batch, not the 32 dead names


def test_epochs_mode_trains_whole_passes(spool, tmp_path):
    status = run(config(spool, tmp_path, steps=None, epochs=2))
    assert status.step == 6  # 2 epochs x 3 batches of 4 from 12 samples
    assert load_checkpoint(tmp_path / "last.pt")["loader"]["epoch"] == 1


def test_sigterm_to_every_process_writes_a_checkpoint_then_exits(spool, tmp_path):
    # The whole process group gets it, loader worker included, as from systemd or `pkill -f`.
    out = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "cuboidtrain", "run", "--spool", str(spool), "--size", str(SIZE), "--batch-size", "4",
         "--out", str(out), "--no-dashboard", "--loader-workers", "1", "--arch", ARCH],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=Path(__file__).parents[1], start_new_session=True,
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not _stepped(out):
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGTERM)
    output = proc.communicate(timeout=60)[0].decode()
    assert proc.returncode == 0, output
    ckpt = load_checkpoint(out / "last.pt")
    assert ckpt["step"] >= 1
    assert json.loads((out / "status.json").read_text())["state"] == "stopped"
    assert not [p for p in os.listdir(out) if p.startswith(".tmp-")]


def _stepped(out: Path) -> bool:
    try:
        return json.loads((out / "status.json").read_text())["step"] >= 1
    except (OSError, ValueError, KeyError):
        return False


def test_cosine_schedule_falls_from_lr_to_a_hundredth():
    cfg = TrainConfig(steps=100, lr=1e-3, lr_schedule="cosine")
    rates = [learning_rate(cfg, s) for s in range(101)]
    assert rates[0] == pytest.approx(1e-3) and rates[-1] == pytest.approx(1e-5)
    assert all(a >= b for a, b in zip(rates, rates[1:]))
    assert learning_rate(TrainConfig(steps=100), 50) == 1e-3


def test_a_schedule_over_minutes_reads_rank_0s_clock_on_every_rank():
    from cuboidtrain.train.loop import schedule_seconds

    class Rank1:  # a torchrun replica: its collective sums every rank's share; rank 0 said 42 s
        main, distributed = False, True

        def sum(self, values):
            assert values == [0.0]  # this rank adds nothing of its own clock
            return [42.0]

    class Alone:
        main, distributed = True, False

    timed = TrainConfig(max_minutes=10, lr_schedule="cosine")
    assert schedule_seconds(timed, Rank1(), started=0.0) == 42.0
    assert 0 < schedule_seconds(timed, Alone(), started=time.monotonic() - 5.0) < 60
    assert schedule_seconds(TrainConfig(steps=100, max_minutes=10, lr_schedule="cosine"), Rank1(), 0.0) == 0.0  # by steps


def test_cosine_schedule_without_steps_runs_out_with_max_minutes():
    cfg = TrainConfig(max_minutes=10, lr=1e-3, lr_schedule="cosine").validate()
    rates = [learning_rate(cfg, 0, elapsed) for elapsed in range(0, 700, 30)]  # the step count plays no part
    assert rates[0] == pytest.approx(1e-3)
    assert learning_rate(cfg, 0, 300) == pytest.approx((1e-3 + 1e-5) / 2)  # half the minutes: half way
    assert rates[-1] == pytest.approx(1e-5)  # past --max-minutes it stays at the floor
    assert all(a >= b for a, b in zip(rates, rates[1:]))


# ---- what --out holds, the path options, the smallest batch (issue 22) --------------------

runner = CliRunner()


def cli_run(spool: Path, out: Path, *extra: str):
    return runner.invoke(app, ["run", "--spool", str(spool), "--size", str(SIZE), "--arch", ARCH, "--batch-size", "4",
                               "--out", str(out), "--no-dashboard", "--loader-workers", "0", "--log-every", "1",
                               *extra])


def test_a_plain_run_into_a_run_folder_is_refused_and_changes_nothing(spool, tmp_path):
    out = tmp_path / "run"
    assert cli_run(spool, out, "--steps", "3").exit_code == 0
    before = {name: (out / name).read_bytes() for name in ("last.pt", "metrics.jsonl", "config.json", "status.json")}
    result = cli_run(spool, out, "--steps", "2")
    assert result.exit_code == 2
    line = result.output.strip()
    assert line == (f"error: --out {out} holds a run (last.pt, metrics.jsonl): --resume continues it, "
                    f"--overwrite starts it over, or give another --out")
    assert {name: (out / name).read_bytes() for name in before} == before  # nothing replaced, nothing truncated
    assert "give one of them" in cli_run(spool, out, "--resume", "--overwrite").output
    assert cli_run(spool, out, "--steps", "4", "--resume").exit_code == 0  # the run goes on: steps 4
    assert load_checkpoint(out / "last.pt")["step"] == 4
    assert cli_run(spool, out, "--steps", "2", "--overwrite").exit_code == 0  # asked: started over
    assert load_checkpoint(out / "last.pt")["step"] == 2
    assert [json.loads(line)["step"] for line in (out / "metrics.jsonl").read_text().splitlines()] == [1, 2]


def test_metrics_alone_are_a_run_too_and_resume_needs_a_checkpoint(spool, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "metrics.jsonl").write_text('{"step": 1}\n')  # killed before its first checkpoint
    assert "holds a run (metrics.jsonl)" in cli_run(spool, out, "--steps", "1").output
    assert "--resume: " in cli_run(spool, tmp_path / "new", "--steps", "1", "--resume").output
    (out / "status.json").write_text("{}")  # status and config alone: nothing to lose
    (out / "metrics.jsonl").unlink()
    assert cli_run(spool, out, "--steps", "1").exit_code == 0


@pytest.mark.parametrize("option, value, expected", [
    ("val_spool", "missing", "--val-spool {}: no such folder"),
    ("spool", "missing", "--spool {}: no such folder"),
    ("init", "missing.pt", "--init {}: no such file"),
])
def test_every_path_option_is_checked_before_any_step(spool, tmp_path, option, value, expected):
    path = tmp_path / value
    cfg = replace(config(spool, tmp_path / "run"), **{option: str(path)}, val_every=1)
    with pytest.raises(UsageError, match=re.escape(expected.format(path))):
        run(cfg)
    assert not (tmp_path / "run").exists()  # nothing written: no step trained, no status left "training"


def test_a_validation_spool_gone_mid_run_costs_no_step(spool, tmp_path, monkeypatch):
    val = tmp_path / "val"
    shutil.copytree(spool, val)
    import cuboidtrain.train.loop as loop

    real, calls = loop.validate, []

    def validate_then_lose_the_spool(*args):
        calls.append(1)
        if len(calls) == 1:
            shutil.rmtree(val)  # gone after the first validation
        return real(*args)

    monkeypatch.setattr(loop, "validate", validate_then_lose_the_spool)
    status = run(config(spool, tmp_path / "run", steps=3, val_spool=str(val), val_every=1, val_samples=4))
    assert status.state == "done" and load_checkpoint(tmp_path / "run" / "last.pt")["step"] == 3
    assert any(note.startswith(f"--val-spool {val}: validation at step 3 failed") for note in status.notes)


def test_a_batch_of_one_trains(spool, tmp_path):
    # Every batch of one was skipped as too small for BatchNorm, which needs two values per
    # channel, not two samples: the run waited for ever on a full spool (issue 22).
    status = run(config(spool, tmp_path / "run", steps=3, batch_size=1, max_wait=5.0))
    assert status.state == "done" and status.step == 3


def test_run_returns_the_typed_status_whose_fields_the_command_line_prints(spool, tmp_path):
    out = tmp_path / "run"
    status = run(config(spool, out, steps=2, checkpoint_every=1))
    assert isinstance(status, TrainerStatus)
    assert (status.state, status.step, status.rank, status.world_size) == ("done", 2, 0, 1)
    assert status.last_checkpoint.path == str(out / "last.pt") and status.last_checkpoint.step == 2
    assert status.to_json() == {**read_status(out).to_json(), "updated": status.updated}  # status.json's figures
    cli_out = tmp_path / ("a_run_folder_whose_name_takes_the_line_past_eighty_columns" * 2)
    result = cli_run(spool, cli_out, "--steps", "2")
    assert result.exit_code == 0, result.output
    assert f"done at step 2; checkpoint {cli_out / 'last.pt'}\n" in result.output  # one line, the path whole


def test_the_least_batch_is_measured_and_a_smaller_one_refused_before_any_step(spool, tmp_path):
    from cuboidtrain.models.networks import build_model
    from cuboidtrain.train.preflight import least_batch

    assert least_batch(tiny_model("box", SIZE), CPU) == 1
    assert least_batch(build_model("box", 32, arch="paper"), CPU) == 2  # ResNet-18's stride 32: a 1x1 map
    assert least_batch(build_model("box", 64, arch="paper"), CPU) == 1
    with pytest.raises(UsageError, match=r"--batch-size 1: the paper arch at --size 32 needs at least 2 samples"):
        run(config(spool, tmp_path / "run", batch_size=1, arch="paper"))
    assert not (tmp_path / "run").exists()
