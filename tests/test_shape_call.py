"""The shape classifier (the fourth network) and who calls a mask's class: its file, its training,
its call in the fit (a rough mask's class; a clean one's stays the silhouette's), the record and trust."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from cuboidgen.config import STREET
from cuboidtrain.cli import app
from cuboidtrain.fit import fitter as fitter_module
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.fit.shape_call import CLASSIFIER, SILHOUETTE, SURE, ShapeCall, call_shape, classifier_input
from cuboidtrain.fit.trust import LIMITS, UNREAD_MARGIN, judge
from cuboidtrain.infer.explain import choice_reason
from cuboidtrain.geometry.mask_fit import polygonal
from cuboidtrain.models.checkpoint import DamagedFile
from cuboidtrain.models.classifier import ShapeClassifier, load_classifier, save_classifier
from cuboidtrain.models.zoo import CLASSIFIER_FILE, cards, shipped_path
from cuboidtrain.train.classifier_training import train_classifier
from shared.errors import UsageError
from shared.sample import decode
from shared.spool import enumerate_spool, read_sample_bytes
from tests.conftest import build_sample, fill_spool

ROOT = Path(__file__).resolve().parents[1]


def seeded_classifier(seed: int = 0) -> ShapeClassifier:
    torch.manual_seed(seed)
    return ShapeClassifier().eval()


class Stub:
    """A classifier that calls every mask it is asked about with one probability, and counts them."""

    def __init__(self, p: float):
        self.p, self.asked = p, 0

    def twobox_probability(self, framed: np.ndarray) -> float:
        assert framed.shape == (64, 64) and framed.dtype == np.float32 and 0 <= framed.min() <= framed.max() <= 1
        self.asked += 1
        return self.p


def test_the_classifier_round_trips_through_its_file_and_calls_a_mirror_alike(tmp_path):
    net = seeded_classifier()
    with torch.no_grad():  # BatchNorm's running statistics as a trained net's, not the identity
        for module in net.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.running_mean.uniform_(-0.1, 0.1)
                module.running_var.uniform_(0.5, 2.0)
    path = tmp_path / "classifier.pt"
    save_classifier(path, net, {"arch": "classifier", "steps": 3})
    loaded, card = load_classifier(path)
    assert card == {"arch": "classifier", "steps": 3}
    for seed in range(4):
        framed = classifier_input(build_sample(seed, ("box", "twobox")[seed % 2], size=96, scene=STREET).noisy)
        p = net.twobox_probability(framed)
        assert 0 < p < 1
        assert loaded.twobox_probability(framed) == pytest.approx(p, abs=2e-3)  # float16 weights in the file
        assert net.twobox_probability(np.ascontiguousarray(framed[:, ::-1])) == pytest.approx(p, abs=1e-6)


def test_a_damaged_or_foreign_classifier_file_is_refused_naming_itself(tmp_path):
    path = tmp_path / "classifier.pt"
    save_classifier(path, seeded_classifier(), {})
    data = bytearray(path.read_bytes())
    weights = data.find(b"data/0") + 200  # inside the first tensor's record
    data[weights] ^= 0x10
    damaged = tmp_path / "damaged.pt"
    damaged.write_bytes(bytes(data))
    with pytest.raises(DamagedFile, match="damaged.pt.*CRC-32"):
        load_classifier(damaged)
    foreign = tmp_path / "foreign.pt"
    torch.save({"format": "cuboid-fit/model", "version": 1}, foreign)
    with pytest.raises(UsageError, match=r"foreign.pt: not a shape classifier"):
        load_classifier(foreign)
    with pytest.raises(UsageError, match="missing.pt: no such file"):
        load_classifier(tmp_path / "missing.pt")


@pytest.fixture(scope="module")
def spools(tmp_path_factory):
    folder = tmp_path_factory.mktemp("classes")
    for shape in ("box", "twobox"):
        fill_spool(folder / shape, 24, shape=shape, size=64)
    return {"box": folder / "box", "twobox": folder / "twobox"}


@pytest.fixture(scope="module")
def trained(spools):
    return train_classifier(spools, steps=45, batch_size=16, seed=0)


def test_training_separates_the_classes_it_was_shown_and_says_how_it_was_trained(spools, trained):
    assert trained.steps == 45 and trained.masks == {"box": 24, "twobox": 24}
    calls = {shape: [trained.net.twobox_probability(classifier_input(build_sample(i, shape, size=64).noisy)) > 0.5
                     for i in range(24)] for shape in ("box", "twobox")}
    right = (calls["box"].count(False) + calls["twobox"].count(True)) / 48
    assert right >= 0.8, calls
    card = trained.card(spools, ["paper"], "abc1234", "a recipe")
    assert card["samples_seen"] == 45 * 16 and card["commit"] == "abc1234" and card["scenes"] == ["paper"]
    assert card["init"] is None


def test_training_on_from_a_file_starts_from_its_weights_and_keeps_its_card(spools, trained, tmp_path):
    first = trained
    save_classifier(tmp_path / "first.pt", first.net, first.card(spools, ["paper"], "abc1234", None))
    on = train_classifier(spools, steps=1, batch_size=16, seed=1, init=tmp_path / "first.pt")
    assert on.card(spools, ["paper"], None, None)["init"]["commit"] == "abc1234"
    scratch = train_classifier(spools, steps=1, batch_size=16, seed=1)

    def distance(other):  # from the file's weights, over the convolutions' and the linear layer's
        ours, theirs = other.net.state_dict(), first.net.state_dict()
        return sum(float((ours[k] - theirs[k]).norm()) for k in ours if k.endswith("weight"))
    # one step from the file's weights stays near them; one from random weights is far away
    assert distance(on) < 0.2 * distance(scratch)
    # a lower peak learning rate moves them less, and the card says which it was
    gentle = train_classifier(spools, steps=1, batch_size=16, seed=1, init=tmp_path / "first.pt", lr=2e-4)
    assert distance(gentle) < 0.5 * distance(on)
    assert gentle.card(spools, ["paper"], None, None)["lr"] == 2e-4 and on.card(spools, [], None, None)["lr"] == 2e-3


def test_training_without_a_span_or_on_an_empty_spool_says_so_in_one_line(spools, tmp_path):
    with pytest.raises(UsageError, match="--minutes or --steps"):
        train_classifier(spools)
    with pytest.raises(UsageError, match="learning rate 0.0: expected more than"):  # before the spools are read
        train_classifier({"box": tmp_path / "absent", "twobox": tmp_path / "absent"}, steps=1, lr=0.0)
    (tmp_path / "empty").mkdir()
    with pytest.raises(UsageError, match="empty: no samples"):
        train_classifier({"box": tmp_path / "empty", "twobox": spools["twobox"]}, steps=1)


def rough(seed: int, shape: str) -> np.ndarray:
    """A generated street mask (occluders, contour noise) that is not one clean polygon."""
    mask = build_sample(seed, shape, size=160, scene=STREET).noisy
    assert call_shape(Stub(0.99), mask).by == CLASSIFIER and not polygonal(mask)
    return mask


@pytest.fixture(scope="module")
def shipped():
    """The shipped box and twobox models with the cuboid fit, the classifier replaced by a stub per test."""
    return Fitter.from_files([shipped_path("box"), shipped_path("twobox")], FitOptions(device="cpu", cuboid=True))


def test_on_a_rough_mask_a_sure_call_outranks_the_iou_and_is_no_guess(shipped, monkeypatch):
    mask = rough(5, "twobox")
    monkeypatch.setattr(shipped, "classifier", None)
    alone = shipped.fit(mask)
    assert alone.shape == "twobox" and alone.record()["shape_call"] is None
    assert alone.candidates["twobox"] > alone.candidates["box"] + 0.04  # the IoU says twobox, clearly
    stub = Stub(0.03)
    monkeypatch.setattr(shipped, "classifier", stub)
    ran = []  # whose networks ran: the twobox's would be dropped unread
    predict = shipped.predict
    monkeypatch.setattr(shipped, "predict", lambda model, *args: ran.append(model.shape) or predict(model, *args))
    fit = shipped.fit(mask)
    assert stub.asked == 1 and fit.shape == "box" and ran == ["box"]
    assert fit.record()["shape_call"] == {"by": "classifier", "twobox_probability": 0.03}
    # its plausible box is taken whatever the twobox explains: fitted alone, the margin unread (the model's
    # mean), and the sure call chose: no guess
    assert set(fit.candidates) == {"box"} and fit.trust.signs["shape_margin"] == UNREAD_MARGIN
    assert "shape-undecided" not in [w.code for w in fit.trust.warnings]
    assert "shape classifier's call" in choice_reason(fit)
    # the same box as when the twobox is fitted beside it; and there the IoU's margin is past the
    # shape-undecided limit, but no guess either
    monkeypatch.setattr(fitter_module, "plausible", lambda cuboid_fit: False)
    both = shipped.fit(mask)
    assert set(both.candidates) == {"box", "twobox"} and both.shape == "box" and ran == ["box", "box", "twobox"]
    np.testing.assert_array_equal(both.keypoints, fit.keypoints)
    assert both.cuboid.fit.ratios == fit.cuboid.fit.ratios
    assert both.trust.signs["shape_margin"] < LIMITS["shape_margin"]
    assert "shape-undecided" not in [w.code for w in both.trust.warnings]


def test_a_gate_outranks_the_call_and_says_so(shipped, monkeypatch):
    monkeypatch.setattr(shipped, "classifier", Stub(0.97))
    fit = shipped.fit(rough(3, "box"))  # its twobox fit is a box with a seam
    assert fit.shape == "box" and fit.shape_call.shape == "twobox"
    assert any(w.startswith("the shape classifier called the mask twobox, but the twobox cuboid was set aside: ")
               for w in fit.warnings), fit.warnings


def test_without_a_classifier_file_the_silhouettes_decide_and_say_it_once(tmp_path, monkeypatch, caplog):
    folder = tmp_path / "models"
    folder.mkdir()
    for shape in ("box", "twobox"):
        (folder / f"{shape}.pt").symlink_to(shipped_path(shape))
    monkeypatch.setenv("CUBOID_MODELS", str(folder))
    with caplog.at_level("WARNING"):
        fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))
        assert fitter.classifier is None and fitter.fit(rough(5, "twobox")).record()["shape_call"] is None
    assert [r.message for r in caplog.records if "no shape classifier" in r.message] == [
        f"no shape classifier at {folder / CLASSIFIER_FILE}: the fitted cuboids' silhouettes alone choose the class"]


def test_on_a_clean_mask_the_silhouette_decides_and_the_classifier_is_not_asked(shipped, monkeypatch):
    for shape in ("box", "twobox"):
        stub = Stub(0.03 if shape == "twobox" else 0.97)  # it would call each wrong
        monkeypatch.setattr(shipped, "classifier", stub)
        fit = shipped.fit(build_sample(1, shape, size=128).clean)
        assert stub.asked == 0 and fit.shape_call == ShapeCall(SILHOUETTE) and fit.shape == shape


def test_an_unsure_call_leaves_the_class_to_the_silhouettes_and_a_sure_one_is_no_guess(shipped, monkeypatch):
    mask = rough(5, "twobox")
    monkeypatch.setattr(shipped, "classifier", None)
    alone = shipped.fit(mask)
    for p in (SURE - 0.02, 1 - SURE + 0.02):  # unsure either way: the fit is the silhouettes' own
        monkeypatch.setattr(shipped, "classifier", Stub(p))
        fit = shipped.fit(mask)
        assert fit.shape_call == ShapeCall(SILHOUETTE, p) and fit.record()["shape_call"]["by"] == "silhouette"
        assert fit.shape == alone.shape and fit.trust == alone.trust
    monkeypatch.setattr(shipped, "classifier", Stub(0.99))
    fit = shipped.fit(mask)
    assert fit.shape == "twobox" and fit.shape_call.shape == "twobox"
    values = dict(fit.trust.signs)
    values["shape_margin"] = -0.5  # the IoU would doubt it; the classifier's sure call is what decided
    assert "shape-undecided" not in [w.code for w in judge(values, fit.shape_call).warnings]
    assert "shape-undecided" in [w.code for w in judge(values, None).warnings]
    assert "shape-undecided" in [w.code for w in judge(values, ShapeCall(SILHOUETTE, 0.6)).warnings]


def test_the_classifier_is_only_asked_with_both_classes_and_the_cuboid_fit(monkeypatch, tmp_path):
    folder = tmp_path / "models"
    folder.mkdir()
    for shape in ("box", "twobox"):
        (folder / f"{shape}.pt").symlink_to(shipped_path(shape))
    save_classifier(folder / CLASSIFIER_FILE, seeded_classifier(), {"shape": "box|twobox", "arch": "classifier"})
    monkeypatch.setenv("CUBOID_MODELS", str(folder))
    assert Fitter.from_shipped(FitOptions(device="cpu", cuboid=True)).classifier is not None
    for options in (FitOptions(device="cpu"), FitOptions(device="cpu", cuboid=True, shape="box"),
                    FitOptions(device="cpu", cuboid=True, shape_classifier=False)):
        assert Fitter.from_shipped(options).classifier is None
    assert sorted(c["shape"] for c in cards(folder)) == ["box", "box|twobox", "twobox"]


def test_the_gpu_recipe_trains_one_that_is_listed_with_the_models_and_used_by_infer(tmp_path, monkeypatch):
    """recipes/classifier.sh as a lent machine runs it (its spools drawn by cuboidgen, `classifier train`), tiny,
    on the CPU; its file in a models folder beside the shipped box and twobox."""
    env = os.environ | {"OUT": str(tmp_path / "out"), "PY": sys.executable, "DEVICE": "cpu", "SAMPLES": "4",
                        "MINUTES": "0.3", "BATCH": "4", "WORKERS": "1", "WORK": str(tmp_path / "work"), "SCENES": "paper",
                        "WHEELS": str(tmp_path / "no-wheels"), "COMMIT": "test"}
    done = subprocess.run([str(ROOT / "recipes" / "classifier.sh")], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    folder = tmp_path / "models"
    folder.mkdir()
    for shape in ("box", "twobox"):
        (folder / f"{shape}.pt").symlink_to(shipped_path(shape))
    (folder / CLASSIFIER_FILE).write_bytes((tmp_path / "out" / CLASSIFIER_FILE).read_bytes())
    runner = CliRunner()
    listed = json.loads(runner.invoke(app, ["models", "--folder", str(folder), "--json"]).output)
    [card] = [c for c in listed if c["file"].endswith(CLASSIFIER_FILE)]
    assert card["arch"] == "classifier" and card["steps"] > 0 and card["masks"] == {"box": 4, "twobox": 4}
    assert card["device"] == "cpu" and card["recipe"].endswith("SIZES='128 256' recipes/classifier.sh at test")
    work = tmp_path / "work" / "box"  # the scene's SAMPLES split over both sizes
    assert sorted(decode(read_sample_bytes(work, name)).size for name in enumerate_spool(work)) == [128] * 2 + [256] * 2
    assert card["scenes"] == ["paper"]
    monkeypatch.setenv("CUBOID_MODELS", str(folder))
    path = tmp_path / "rough.png"
    assert cv2.imwrite(str(path), rough(3, "twobox").astype(np.uint8) * 255)
    out = tmp_path / "records.json"
    assert runner.invoke(app, ["infer", str(path), "--json", str(out)]).exit_code == 0
    assert 0 < json.loads(out.read_text())[0]["shape_call"]["twobox_probability"] < 1  # asked (3 steps: unsure)
    assert runner.invoke(app, ["infer", str(path), "--json", str(out), "--no-classifier"]).exit_code == 0
    assert json.loads(out.read_text())[0]["shape_call"] is None
