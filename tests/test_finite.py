"""No NaN or Infinity ever reaches a record, a report, a checkpoint or a JSON file: the trainer
stops on a non-finite loss or weight, keeping its last finite checkpoint; a checkpoint with such
weights is neither written nor read; the one JSON writer refuses them, naming where they lie."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

import cuboidtrain.train.loop as loop
from cuboidtrain.cli import app as train_app
from cuboidtrain.models.checkpoint import load_checkpoint, save_checkpoint
from cuboidtrain.train.loop import Diverged, run
from shared.files import json_text, non_finite, write_json
from tests.conftest import fill_spool, tiny_model, train_config

SIZE = 32
runner = CliRunner()


def strict_loads(text: str):
    """json.loads as a strict parser reads: the bare NaN and Infinity tokens are errors."""
    def refuse(token):
        raise ValueError(f"{token} is not JSON")
    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def spool(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("spool")
    fill_spool(path, 8, size=SIZE)
    return path


def config(spool: Path, out: Path, **changes):
    base = train_config(spool=str(spool), out=str(out), shape="box", size=SIZE, steps=8, batch_size=4,
                        loader_workers=0, dashboard=False, log_every=1, checkpoint_every=2)
    return replace(base, **changes).validate()


def poison_losses_from(monkeypatch, call: int) -> None:
    """From the `call`-th step on, D_T is NaN: its gradients turn every weight they reach NaN."""
    original, calls = loop.phase_losses, []

    def poisoned(*args, **kwargs):
        losses = original(*args, **kwargs)
        calls.append(1)
        return losses | {"D_T": losses["D_T"] * float("nan")} if len(calls) >= call else losses
    monkeypatch.setattr(loop, "phase_losses", poisoned)


@pytest.mark.parametrize("poison", ["loss", "weights"])
def test_the_trainer_stops_on_a_non_finite_loss_or_weight_and_keeps_its_last_finite_checkpoint(
        spool, tmp_path, monkeypatch, poison):
    if poison == "loss":
        poison_losses_from(monkeypatch, 5)
    else:  # finite losses, then a step that overflows a weight
        original, calls = loop.train_step, []

        def overflowing(model, *args, **kwargs):
            losses = original(model, *args, **kwargs)
            calls.append(1)
            if len(calls) == 5:
                with torch.no_grad():
                    next(model.parameters()).view(-1)[0] = float("inf")
            return losses
        monkeypatch.setattr(loop, "train_step", overflowing)
    out = tmp_path / "run"
    with pytest.raises(Diverged) as caught:
        run(config(spool, out))
    message = str(caught.value)
    assert message.startswith("training diverged at step 5: ") and "\n" not in message
    assert ("D_T is nan" if poison == "loss" else "1 of ") in message
    assert f"{out}/last.pt keeps step 4" in message
    kept = load_checkpoint(out / "last.pt")
    assert kept["step"] == 4 and all(torch.isfinite(t).all() for t in kept["model"].values() if t.is_floating_point())
    status = strict_loads((out / "status.json").read_text())
    assert status["state"] == "failed" and status["step"] == 4
    records = [strict_loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2, 3, 4]


def test_run_says_so_in_one_line_and_exits_non_zero(spool, tmp_path, monkeypatch):
    poison_losses_from(monkeypatch, 1)
    out = tmp_path / "run"
    result = runner.invoke(train_app, ["run", "--spool", str(spool), "--size", str(SIZE), "--arch", "tiny",
                                       "--batch-size", "4", "--steps", "4", "--loader-workers", "0",
                                       "--no-dashboard", "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert "training diverged at step 1" in lines[0] and "no checkpoint was written" in lines[0]
    assert not (out / "last.pt").exists()


def nan_model(path: Path) -> Path:
    """A checkpoint as an older trainer left a diverged run: weights NaN, written without the check."""
    model = tiny_model("box", SIZE)
    good = path.with_suffix(".good.pt")
    save_checkpoint(good, model, train_config(shape="box", size=SIZE), 4)
    ckpt = torch.load(good, weights_only=False)
    ckpt["model"] = {k: v * float("nan") if v.is_floating_point() else v for k, v in ckpt["model"].items()}
    torch.save(ckpt, path)
    return path


def test_a_checkpoint_of_non_finite_weights_is_neither_written_nor_read(tmp_path):
    model = tiny_model("box", SIZE)
    with torch.no_grad():
        next(model.parameters()).view(-1)[:3] = float("nan")
    with pytest.raises(ValueError, match=r"not written at step 7: 3 of \d+ weights are NaN or Infinity"):
        save_checkpoint(tmp_path / "last.pt", model, train_config(shape="box", size=SIZE), 7)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match=r"weights are NaN or Infinity \(a diverged training\): not a model to use"):
        load_checkpoint(nan_model(tmp_path / "nan.pt"))


@pytest.mark.parametrize("command", ["eval", "infer"])
def test_eval_and_infer_refuse_a_diverged_checkpoint_in_one_line(spool, tmp_path, command):
    checkpoint = nan_model(tmp_path / "nan.pt")
    args = (["eval", "--spool", str(spool)] if command == "eval" else ["infer", "examples/building.png"])
    result = runner.invoke(train_app, [*args, "--checkpoint", str(checkpoint), "--device", "cpu"])
    assert result.exit_code == 2 and result.output.count("\n") == 1, result.output
    assert "weights are NaN or Infinity" in result.output and "nan," not in result.output


def test_a_fit_that_gives_a_non_finite_value_is_an_error_record(monkeypatch):
    from cuboidtrain.fit.fitter import Fitter, FitFailure
    from cuboidtrain.fit.options import FitOptions
    from cuboidtrain.infer.records import to_records

    model = tiny_model("box", SIZE)
    with torch.no_grad():  # a model in hand, not from a file: nothing checked its weights
        for p in model.tabulator.parameters():
            p.fill_(float("nan"))
    outcomes = Fitter([model], FitOptions(device="cpu")).outcomes(["examples/building.png"])
    assert len(outcomes) == 1 and isinstance(outcomes[0], FitFailure)
    records = to_records(outcomes, FitOptions())
    assert records[0]["keypoints"] is None and records[0]["confidence"] is None
    assert "not finite" in records[0]["error"]
    strict_loads(json_text(records))


def test_the_json_writer_refuses_nan_and_infinity_naming_where_they_lie(tmp_path):
    data = {"records": [{"keypoints": [[1.0, 2.0], [float("nan"), 3.0]]}], "loss": 1.5}
    assert non_finite(data) == ("records[0].keypoints[1][0]", pytest.approx(float("nan"), nan_ok=True))
    with pytest.raises(ValueError, match=r"^out.json: records\[0\].keypoints\[1\]\[0\] is nan, which JSON cannot hold"):
        json_text(data, what="out.json")
    with pytest.raises(ValueError, match=r"loss is inf"):
        write_json(tmp_path / "x.json", {"loss": float("inf")})
    assert list(tmp_path.iterdir()) == []  # nothing written, no temporary file left
    assert strict_loads(json_text(data | {"records": []})) == {"records": [], "loss": 1.5}


def test_no_json_is_written_but_through_the_one_writer():
    """json.dump(s) anywhere else would write bare NaN tokens again: only shared/files.py calls it."""
    root = Path(__file__).resolve().parent.parent
    calls = [f"{path.relative_to(root)}:{number}"
             for package in ("shared", "cuboidgen", "cuboidtrain")
             for path in sorted((root / package).rglob("*.py"))
             for number, line in enumerate(path.read_text().splitlines(), 1)
             if "json.dump" in line and path != root / "shared" / "files.py"]
    assert calls == []


def test_eval_never_reports_a_non_finite_metric(spool):
    from cuboidtrain.train.evaluate import evaluate
    from cuboidtrain.fit.options import FitOptions
    from shared.errors import UsageError

    model = tiny_model("box", SIZE)
    with torch.no_grad():  # a model in hand (a trainer's mid-run validation): its weights unchecked
        for p in model.tabulator.parameters():
            p.fill_(float("inf"))
    with pytest.raises(UsageError, match=r"^evaluation of the box model: \w+ is (nan|inf|-inf): its outputs"):
        evaluate(model, spool, 1.0, FitOptions(device="cpu", extractor="tabulator"), max_samples=4)
