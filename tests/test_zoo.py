"""Model files and the shipped models (cuboidtrain.models.zoo): pack round trips, cards, defaults, errors."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from cuboidtrain.models.checkpoint import MODEL_FORMAT, load_checkpoint, load_model, save_checkpoint
from cuboidtrain.cli import app
from cuboidtrain.models.zoo import SHIPPED_SHAPES, cards, pack, shipped_path
from cuboidtrain.models.codec import make_codec
from tests.conftest import write_mask_pngs
from cuboidtrain.models.pdm import MIN_SAMPLES
from shared.sample import encode
from shared.spool import SpoolWriter
from tests.conftest import SIZE, build_sample, fill_spool, tiny_model, train_config

runner = CliRunner()


@pytest.fixture(scope="module")
def zoo(tmp_path_factory):
    """A folder of packed tiny models, one per shipped shape, and their training checkpoints."""
    root = tmp_path_factory.mktemp("zoo")
    checkpoints = {}
    for k, shape in enumerate(SHIPPED_SHAPES):
        model = tiny_model(shape, seed=k + 1).eval()
        # BatchNorm statistics that are not the defaults, so a lost buffer would show
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
        config = train_config(shape=shape, size=SIZE, out=str(root / f"run-{shape}"))
        checkpoints[shape] = save_checkpoint(root / f"run-{shape}" / "last.pt", model, config, step=40,
                                             optimizer=torch.optim.Adam(model.parameters()))
        pack(checkpoints[shape], root / "models" / f"{shape}.pt", ["paper", "street"], recipe="test")
    return root / "models", checkpoints


def test_a_packed_model_gives_the_checkpoints_outputs_to_float16_precision(zoo):
    folder, checkpoints = zoo
    original, _ = load_model(checkpoints["box"])
    packed, payload = load_model(folder / "box.pt")
    assert payload["format"] == MODEL_FORMAT and payload["arch"] == original.arch == packed.arch
    assert "optimizer" not in payload and "rng" not in payload  # weights, config and card only
    x = torch.from_numpy(np.where(build_sample(3).noisy, 1.0, -1.0).astype(np.float32))[None, None]
    with torch.no_grad():
        a, b = original(x), packed(x)
    assert torch.allclose(a.heatmaps, b.heatmaps, atol=5e-3)
    assert (a.keypoints - b.keypoints).abs().max() < 0.05  # px
    assert all(v.dtype == torch.float16 for v in payload["model"].values() if v.is_floating_point())


def test_the_card_says_how_the_model_was_made(zoo):
    folder, _ = zoo
    card = load_checkpoint(folder / "twobox.pt")["card"]
    assert card["shape"] == "twobox" and card["arch"] == "tiny" and card["size"] == SIZE
    assert card["scenes"] == ["paper", "street"] and card["recipe"] == "test"
    assert card["steps"] == 40 and card["samples_seen"] == 40 * card["phases"][0]["batch_size"]


def test_a_continued_model_card_keeps_the_phases_of_the_model_it_continued(tmp_path):
    """CONTINUE=1 recipes/shipped.sh: phase 2 again from a shipped model file (--init), whose
    training checkpoints are long gone (a fresh clone has no runs/). The new card lists the
    shipped model's phases from its card, then the continuation's, and sums them."""
    import shutil

    model = tiny_model("box", seed=5)
    p1 = save_checkpoint(tmp_path / "p1" / "last.pt", model,
                         train_config(shape="box", size=SIZE, out=str(tmp_path / "p1")), step=40)
    p2 = save_checkpoint(tmp_path / "p2" / "last.pt", model,
                         train_config(shape="box", size=SIZE, phase="2", init=str(p1), out=str(tmp_path / "p2")),
                         step=30)
    shipped = pack(p2, tmp_path / "shipped.pt", ["paper"], recipe="shipped")
    assert [(p["phase"], p["steps"]) for p in shipped["phases"]] == [("1", 40), ("2", 30)]
    shutil.rmtree(tmp_path / "p1"), shutil.rmtree(tmp_path / "p2")
    config = train_config(shape="box", size=SIZE, phase="2", init=str(tmp_path / "shipped.pt"),
                          out=str(tmp_path / "continued"))
    continued = save_checkpoint(tmp_path / "continued" / "last.pt", model, config, step=25)
    card = pack(continued, tmp_path / "box.pt", ["paper"], recipe="continued")
    assert [(p["phase"], p["steps"]) for p in card["phases"]] == [("1", 40), ("2", 30), ("2", 25)]
    assert card["phases"][:2] == shipped["phases"]
    assert card["steps"] == 95 and card["samples_seen"] == 95 * config.batch_size


def test_packing_a_model_file_again_is_refused(zoo, tmp_path):
    folder, _ = zoo
    with pytest.raises(ValueError, match="already a model file.*or give --pdm-spool"):
        pack(folder / "box.pt", tmp_path / "again.pt", [])


def test_a_pdm_is_fitted_on_the_training_spool_and_travels_in_the_model_file(zoo, tmp_path):
    folder, _ = zoo
    spool = tmp_path / "spool"
    with SpoolWriter(spool, limit=0) as writer:  # 16 px: the PDM normalises position and scale away
        for seed in range(MIN_SAMPLES):
            writer.publish(encode(build_sample(seed, "box", size=16)))
    runner_result = runner.invoke(app, ["models", "pack", "--checkpoint", str(folder / "box.pt"),
                                        "--out", str(tmp_path / "box.pt"), "--pdm-spool", str(spool)])
    assert runner_result.exit_code == 0, runner_result.output
    before, _ = load_model(folder / "box.pt")
    after, payload = load_model(tmp_path / "box.pt")
    assert before.pdm is None and payload["card"]["pdm"] == {"spool": str(spool), "keypoint_sets": MIN_SAMPLES}
    assert all(torch.equal(before.state_dict()[k], v) for k, v in after.state_dict().items())  # weights stay
    truth = np.stack([build_sample(seed, "box", size=16).keypoints for seed in range(5)])
    assert np.allclose(after.pdm.project(truth, 16), truth, atol=1e-6)  # every component: exact
    make_codec("pdm", after)  # the codec finds the file's shape model


def test_too_small_a_pdm_spool_is_a_one_line_error(zoo, tmp_path):
    folder, checkpoints = zoo
    spool = tmp_path / "spool"
    fill_spool(spool, 3)
    with pytest.raises(ValueError, match=f"3 box samples, a point distribution model needs at least {MIN_SAMPLES}"):
        pack(checkpoints["box"], tmp_path / "box.pt", [], pdm_spool=spool)


def test_models_lists_the_cards(zoo):
    folder, _ = zoo
    result = runner.invoke(app, ["models", "--folder", str(folder), "--json"])
    assert result.exit_code == 0, result.output
    listed = json.loads(result.output)
    assert [c["shape"] for c in listed] == ["box", "twobox"] and all(c["bytes"] > 0 for c in listed)
    table = runner.invoke(app, ["models", "--folder", str(folder)], env={"COLUMNS": "160"})
    assert table.exit_code == 0 and "paper+street" in table.output and "tiny" in table.output


def test_infer_without_a_checkpoint_uses_the_shipped_models(zoo, tmp_path, monkeypatch):
    import cv2

    folder, _ = zoo
    monkeypatch.setenv("CUBOID_MODELS", str(folder))
    mask = tmp_path / "m.png"
    cv2.imwrite(str(mask), build_sample(5, size=96).noisy.astype(np.uint8) * 255)
    result = runner.invoke(app, ["infer", str(mask), "--json", "-", "--networks-only"])
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)[0]  # stdout: the answer line and the total are on stderr
    assert set(record["candidates"]) == {"box", "twobox"}  # both shipped models were tried
    given = runner.invoke(app, ["infer", str(mask), "--checkpoint", str(folder / "box.pt"), "--json", "-",
                                "--networks-only"])
    assert json.loads(given.stdout)[0]["keypoints"] == json.loads(
        runner.invoke(app, ["infer", str(mask), "--shape", "box", "--json", "-", "--networks-only"]).stdout)[0]["keypoints"]


def test_a_missing_shipped_model_is_a_one_line_error(tmp_path, monkeypatch):
    monkeypatch.setenv("CUBOID_MODELS", str(tmp_path))
    with pytest.raises(ValueError, match="shipped model .*box.pt: no such file"):
        shipped_path("box")
    result = runner.invoke(app, ["infer", "anything.png", "--json", "-"])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code != 0 and len(lines) == 1 and "no such file" in lines[0], result.output


def test_a_corrupt_shipped_model_is_a_one_line_error(tmp_path, monkeypatch):
    (tmp_path / "box.pt").write_bytes(b"not a model at all")
    (tmp_path / "twobox.pt").write_bytes(b"")
    monkeypatch.setenv("CUBOID_MODELS", str(tmp_path))
    mask = write_mask_pngs(tmp_path, 1)[0]  # a real input: inputs are checked before the models load
    result = runner.invoke(app, ["infer", mask, "--json", "-"])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code != 0 and len(lines) == 1 and "box.pt" in lines[0], result.output
    with pytest.raises(ValueError, match="box.pt"):
        cards(tmp_path)


def test_a_model_file_starts_a_training_run(zoo):
    # --init takes a model file, so a recipe can continue the shipped weights
    folder, _ = zoo
    ckpt = load_checkpoint(folder / "box.pt", shape="box", size=SIZE, arch="tiny")
    model = tiny_model("box", seed=9)
    model.load_state_dict(ckpt["model"])  # float16 weights load into a float32 model
    assert all(p.dtype == torch.float32 for p in model.parameters())
    with pytest.raises(ValueError, match="'tiny' arch model, expected 'compact'"):
        load_checkpoint(folder / "box.pt", arch="compact")


def test_a_model_file_with_a_flipped_bit_is_refused_by_models_and_infer_naming_it(tmp_path):
    # torch.load itself reads such a file: the flipped bit becomes a changed weight, silently
    folder = tmp_path / "models"
    folder.mkdir()
    damaged = folder / "box.pt"
    data = bytearray(shipped_path("box").read_bytes())
    data[len(data) // 2] ^= 0x01
    damaged.write_bytes(bytes(data))
    assert torch.load(damaged, map_location="cpu", weights_only=False)["shape"] == "box"  # what it guards against
    for args in (["models", "--folder", str(folder)],
                 ["infer", "examples/building.png", "--checkpoint", str(damaged), "--json", "-"]):
        result = runner.invoke(app, args)
        lines = [line for line in result.output.splitlines() if line.strip()]
        assert result.exit_code == 2 and len(lines) == 1, result.output
        assert f"{damaged}: damaged: " in lines[0] and "CRC-32" in lines[0], lines[0]
