"""Evaluation: the metric functions on hand-made values, and `evaluate` on tiny spools."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from cuboidtrain.models.checkpoint import save_checkpoint
from cuboidtrain.train.evaluate import evaluate, evaluate_checkpoint, format_report, keypoint_errors, mask_iou
from cuboidtrain.models.codec import render_heatmaps
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.models.networks import ChainOutput
from shared.sample import encode, signed
from shared.shapes import get_shape
from shared.spool import SpoolWriter
from tests.conftest import build_sample, tiny_model, train_config, with_generated_pdm

SIZE = 32  # px: the smallest size a ResNet-18 model takes
CPU = torch.device("cpu")
KEYS = {
    "mean_px_error", "median_px_error", "per_keypoint_px_error", "pck", "mean_ratio_error", "per_ratio_error",
    "refiner_iou", "tabulator_px_error_on_true_heatmaps", "samples", "skipped", "shape", "size",
}


def publish(spool: Path, samples) -> None:
    with SpoolWriter(spool, limit=0) as writer:
        for sample in samples:
            writer.publish(encode(sample))


@pytest.fixture(scope="module")
def box_samples():
    return [build_sample(seed, "box", size=SIZE) for seed in range(6)]


@pytest.fixture(scope="module")
def box_spool(tmp_path_factory, box_samples) -> Path:
    spool = tmp_path_factory.mktemp("val")
    publish(spool, box_samples)
    return spool


# --- the metric functions ---------------------------------------------------------------------


def test_keypoint_errors_are_euclidean_px():
    pred = torch.tensor([[[0.0, 0.0], [10.0, 10.0]], [[1.5, 2.0], [-3.0, 0.0]]])
    true = torch.tensor([[[3.0, 4.0], [10.0, 10.0]], [[1.5, 2.0], [0.0, 4.0]]])
    assert torch.allclose(keypoint_errors(pred, true), torch.tensor([[5.0, 0.0], [0.0, 5.0]]))


def test_keypoint_errors_reject_mismatched_shapes():
    with pytest.raises(ValueError, match=r"\(1, 8, 2\) and \(1, 14, 2\)"):
        keypoint_errors(torch.zeros(1, 8, 2), torch.zeros(1, 14, 2))


def test_mask_iou_on_hand_made_masks():
    clean = -torch.ones(4, 1, 2, 2)
    refined = -torch.ones(4, 1, 2, 2)
    clean[0, 0, 0, :] = 1; refined[0, 0, 0, :] = 0.3  # identical objects (refined > 0 is object)
    clean[1, 0, 0, 0] = 1; refined[1, 0, 1, 1] = 0.9  # disjoint
    clean[2, 0, 0, :] = 1; refined[2, 0, :, 0] = 0.5  # overlap 1 of union 3
    refined[3, 0, 0, 0] = -0.01  # both empty: they agree
    assert torch.allclose(mask_iou(refined, clean), torch.tensor([1.0, 0.0, 1 / 3, 1.0]))


# --- evaluate --------------------------------------------------------------------------------


def test_evaluate_reports_every_metric_in_range(box_spool):
    model = tiny_model("box", SIZE, seed=0).train()
    result = evaluate(model, box_spool, sigma=1.0, options=FitOptions(device="cpu"), batch_size=4)  # batches of 4 and 2
    assert KEYS <= set(result.to_dict())  # eval --json's object
    assert (result.shape, result.size, result.samples) == ("box", SIZE, 6)
    assert not any(result.skipped.values())
    assert 0 <= result.median_px_error and 0 <= result.mean_px_error < SIZE * math.sqrt(2)
    geometry = get_shape("box")
    assert list(result.per_keypoint_px_error) == list(geometry.keypoint_names)
    assert np.mean(list(result.per_keypoint_px_error.values())) == pytest.approx(result.mean_px_error)
    assert list(result.per_ratio_error) == list(geometry.ratio_names)
    assert result.mean_ratio_error >= 0 and result.tabulator_px_error_on_true_heatmaps >= 0
    assert 0 <= result.refiner_iou <= 1
    pck = list(result.pck.values())
    assert list(result.pck) == ["0.5", "1.0", "2.0", "5.0"]
    assert all(0 <= p <= 1 for p in pck) and pck == sorted(pck)
    assert model.training, "evaluate must hand a training model back in train mode"


def test_evaluate_is_deterministic_and_independent_of_batch_size(box_spool):
    model = tiny_model("box", SIZE, seed=1)
    a = evaluate(model, box_spool, sigma=1.0, options=FitOptions(device="cpu"), batch_size=6)
    b = evaluate(model, box_spool, sigma=1.0, options=FitOptions(device="cpu"), batch_size=1)
    assert a.mean_px_error == pytest.approx(b.mean_px_error, rel=1e-5)
    assert a.refiner_iou == pytest.approx(b.refiner_iou, rel=1e-5)


class CentroidTabulator(nn.Module):
    """Heat maps -> their centres of mass (pixel-centre convention), ratios 0."""

    def forward(self, heatmaps: torch.Tensor):
        b, n, h, w = heatmaps.shape
        mass = heatmaps.sum(dim=(-2, -1))  # (B, N)
        x = (heatmaps.sum(-2) * torch.arange(w)).sum(-1) / mass
        y = (heatmaps.sum(-1) * torch.arange(h)).sum(-1) / mass
        return torch.stack([x, y], dim=-1), torch.zeros(b, 2)


class Oracle(nn.Module):
    """Answers each noisy mask with the truth of the sample it was drawn with.

    It looks the mask up by its pixels, so if evaluate compared a sample's
    prediction with another sample's keypoints, or shifted the convention, the
    errors would not be zero.
    """

    def __init__(self, samples, shape: str, size: int):
        super().__init__()
        self.shape, self.size, self.sigma, self.grey_input = shape, size, 1.0, False
        self.truth = {s.noisy.tobytes(): s for s in samples}
        self.tabulator = CentroidTabulator()

    def forward(self, mask: torch.Tensor, refine_steps: int | None = 1) -> ChainOutput:
        found = [self.truth[(m[0] > 0).numpy().tobytes()] for m in mask]
        geometry = get_shape(self.shape)
        keypoints = torch.tensor(np.stack([s.keypoints for s in found]), dtype=torch.float32)
        return ChainOutput(
            refined=torch.from_numpy(np.stack([signed(s.clean) for s in found]))[:, None],
            heatmaps=render_heatmaps(torch.tensor(np.stack([s.keypoints for s in found])), self.size, self.sigma),
            keypoints=keypoints, tabulated=keypoints,
            ratios=torch.tensor(np.stack([geometry.ratio_vector(s.ratios) for s in found]), dtype=torch.float32),
            refine_steps=1, refine_converged=True,
        )


def test_an_oracle_scores_perfectly(box_spool, box_samples):
    result = evaluate(Oracle(box_samples, "box", SIZE), box_spool, sigma=1.0, options=FitOptions(device="cpu"), batch_size=4)
    assert result.samples == 6
    assert result.mean_px_error == pytest.approx(0, abs=1e-5)
    assert result.median_px_error == pytest.approx(0, abs=1e-5)
    assert all(p == 1.0 for p in result.pck.values())
    assert result.mean_ratio_error == pytest.approx(0, abs=1e-6)
    assert result.refiner_iou == 1.0
    # x3 is rendered at x4 in the pixel-centre convention: its centroid lands on it (a 0.5 px slip would show)
    assert result.tabulator_px_error_on_true_heatmaps < 0.05


@pytest.mark.parametrize("extractor, bound", [("dark", 0.01), ("centre-of-mass", 0.2), ("argmax", 0.71), ("pdm", 0.5)])
def test_an_oracles_heat_maps_decode_to_the_truth_with_every_extractor(box_spool, box_samples, extractor, bound):
    # The Oracle's S draws the true maps: each extractor then shows its own decoding error, and
    # argmax its half-pixel grid (at most sqrt(2)/2 px).
    oracle = with_generated_pdm(Oracle(box_samples, "box", SIZE))
    result = evaluate(oracle, box_spool, sigma=1.0, options=FitOptions(device="cpu", extractor=extractor))
    assert result.extractor == extractor
    assert result.mean_px_error < bound
    assert result.extractor_px_error_on_true_heatmaps == pytest.approx(result.mean_px_error, abs=1e-5)


def test_evaluate_skips_and_counts_other_samples(tmp_path):
    spool = tmp_path / "mix"
    publish(spool, [build_sample(0, "twobox", size=SIZE), build_sample(1, "box", size=SIZE),
                    build_sample(2, "box", size=64), build_sample(3, "box", size=SIZE),
                    build_sample(4, "box", size=SIZE)])
    (spool / "0000000000000000001-junk.cub").write_bytes(b"not a sample")  # sorts first
    model = tiny_model("box", SIZE)
    result = evaluate(model, spool, sigma=1.0, options=FitOptions(device="cpu"))
    # the 64 px box is framed at the model's size as infer frames a mask: evaluated, not skipped
    assert result.samples == 4
    assert result.skipped == {"vanished": 0, "damaged": 0, "corrupt": 1, "other_shape": 1, "other_size": 0, "cut_off": 0}
    first_two = evaluate(model, spool, sigma=1.0, options=FitOptions(device="cpu"), batch_size=1, max_samples=2)
    assert first_two.samples == 2  # the first two box samples, past the others


def test_a_spool_without_the_models_samples_is_a_clear_error(tmp_path):
    spool = tmp_path / "val"
    publish(spool, [build_sample(i, "twobox", size=SIZE) for i in range(2)])
    model = tiny_model("box", SIZE)
    with pytest.raises(ValueError, match=r"spool .*val: 0 box 32 px samples among 2 \(2 twobox 32 px\)"):
        evaluate(model, spool, sigma=1.0, options=FitOptions(device="cpu"))
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="empty, no box 32 px samples"):
        evaluate(model, empty, sigma=1.0, options=FitOptions(device="cpu"))


def test_evaluate_checkpoint_reports_the_random_weights_row(tmp_path, box_spool):
    config = train_config(shape="box", size=SIZE, steps=1, sigma=1.5)
    path = save_checkpoint(tmp_path / "random.pt", tiny_model("box", SIZE, seed=3), config, step=7)
    result = evaluate_checkpoint(path, box_spool, FitOptions(device="cpu"), max_samples=4, random_init_seed=3)
    assert {"random_init_mean_px_error", "random_init_median_px_error", "checkpoint", "step", "spool"} <= set(
        result.to_dict())  # eval --json's object
    assert (result.reference.step, result.samples, result.sigma) == (7, 4, 1.5)
    assert result.mean_px_error == result.reference.random_init_mean_px_error
    assert result.median_px_error == result.reference.random_init_median_px_error
    other = evaluate_checkpoint(path, box_spool, FitOptions(device="cpu"), max_samples=4, random_init_seed=4)
    assert other.reference.random_init_mean_px_error != other.mean_px_error
    report = format_report(result)
    assert "random init" in report and "BACK-RIGHT-TOP" in report and "step 7" in report


@pytest.fixture(scope="module")
def spool_of_another_size(tmp_path_factory) -> Path:
    """64 px box samples for SIZE px models: eval frames each as infer frames a mask."""
    spool = tmp_path_factory.mktemp("val64")
    publish(spool, [build_sample(seed, "box", size=64) for seed in range(4)])
    return spool


@pytest.mark.parametrize("margin", [0.0, 0.1, 0.25])
def test_eval_frames_samples_of_another_size_with_its_margin(spool_of_another_size, margin):
    from cuboidtrain.data.prepare import prepare_batch
    from cuboidtrain.train.evaluate import load_batches

    batches, skipped = load_batches(spool_of_another_size, "box", SIZE, 4, None, margin)
    assert sum(len(b.names) for b in batches) + skipped["cut_off"] == 4
    for batch in batches:  # framed on the device, as the batches are measured
        for mask in prepare_batch(batch, torch.device("cpu"), 1.0, SIZE).x1[:, 0].numpy() > 0:
            ys, xs = np.nonzero(mask)
            longer = max(ys.max() - ys.min(), xs.max() - xs.min()) + 1
            assert abs(longer - SIZE * (1 - 2 * margin)) <= 1.5  # the object spans the frame less two margins


def test_evaluate_honours_the_fit_options_margin(spool_of_another_size):
    model = tiny_model("box", SIZE, seed=3).eval()
    errors = {margin: evaluate(model, spool_of_another_size, sigma=1.0,
                               options=FitOptions(device="cpu", margin=margin)).mean_px_error
              for margin in (0.1, 0.3)}
    assert errors[0.1] != errors[0.3]  # another framing, other inputs, other answers


# --- the paths a user gets: networks only against the cuboid fit ------------------------------------

PATH_FIGURES = ("mean_px", "median_px", "hull_mean_px", "interior_mean_px", "nme_mean", "depth_height_mean_rel",
                "width_height_mean_rel", "yaw_mean_deg", "yaw_median_deg", "iou3d_mean", "iou3d_median",
                "focal_median_rel")


def test_an_oracle_scores_both_paths_near_the_truth(box_spool, box_samples):
    oracle = Oracle(box_samples, "box", SIZE)
    result = evaluate(oracle, box_spool, sigma=1.0, options=FitOptions(device="cpu", cuboid=True), batch_size=4,
                      paths=True)
    networks, cuboid = result.paths["networks"], result.paths["cuboid"]
    assert networks["samples"] == cuboid["samples"] == 6 and networks["failed"] == 0
    assert networks["mean_px"] == pytest.approx(0, abs=1e-5)  # the truth's corners, back in the sample's px
    assert networks["posed"] == 6 and networks["yaw_median_deg"] < 0.01 and networks["iou3d_median"] > 0.999
    assert cuboid["failed"] == 0 and cuboid["median_px"] < 2.0  # the cuboid fitted to the noisy mask from there
    assert all(isinstance(cuboid[k], float) and math.isfinite(cuboid[k]) for k in PATH_FIGURES)
    without = evaluate(oracle, box_spool, sigma=1.0, options=FitOptions(device="cpu"), paths=True)
    assert list(without.paths) == ["networks"]  # the cuboid path only where the options ask for it
    plain = evaluate(oracle, box_spool, sigma=1.0, options=FitOptions(device="cpu"))
    assert plain.paths is None and "paths" not in plain.to_dict()


def test_eval_cuboid_reports_both_paths_with_finite_numbers(tmp_path):
    from typer.testing import CliRunner

    from cuboidtrain.cli import app
    from tests.conftest import fill_spool

    spool = tmp_path / "spool"
    fill_spool(spool, 5, size=48)  # framed at the model's 32 px as infer frames a mask; scored in their own 48 px
    config = train_config(shape="box", size=SIZE, steps=1, sigma=1.5)
    checkpoint = save_checkpoint(tmp_path / "model.pt", tiny_model("box", SIZE, seed=2), config, step=1)
    args = ["eval", "--spool", str(spool), "--checkpoint", str(checkpoint), "--device", "cpu", "--cuboid"]
    result = CliRunner().invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    paths = json.loads(result.output)["paths"]
    assert list(paths) == ["networks", "cuboid", "cuboid_camera_given"]
    assert all(0 <= paths[name][k] <= 1 for name in ("cuboid", "cuboid_camera_given") for k in ("within_1sd", "within_2sd"))
    for figures in paths.values():
        assert figures["samples"] == 5 and figures["posed"] == 5 - figures["failed"]
        assert all(isinstance(figures[k], float) and math.isfinite(figures[k]) for k in PATH_FIGURES), figures
        assert 0 <= figures["iou3d_mean"] <= 1 and 0 <= figures["yaw_mean_deg"] <= 90
    table = CliRunner().invoke(app, args)
    assert table.exit_code == 0 and "3D IoU" in table.output and "cuboid" in table.output, table.output


def test_eval_scores_the_very_fits_infer_gives(tmp_path):
    """One pipeline: each sample's cuboid path in `eval --cuboid` is the answer `Fitter.fit` (what
    `infer` runs) gives for that sample's mask, though eval fits a batch of samples at once."""
    from cuboidtrain.fit.fitter import Fitter
    from cuboidtrain.geometry.accuracy import Truth, against_truth
    from cuboidtrain.train.evaluate import load_batches, measure

    spool = tmp_path / "val"
    publish(spool, [build_sample(seed, "box", size=128) for seed in range(3)])  # each fitted three times: a few
    options = FitOptions(device="cpu", cuboid=True, shape="box")
    fitter = Fitter.from_shipped(options)
    [model] = fitter.models
    batches, _ = load_batches(spool, "box", model.size, 2, None, options.margin, keep_sources=True)
    assert [len(batch.sources) for batch in batches] == [2, 1]  # a full batch and the rest
    scored = measure(model, batches, model.sigma, options, paths=True)["paths"]
    sources = [source for batch in batches for source in batch.sources]
    assert len(sources) == len(scored["cuboid"]) == 3
    for source, networks, cuboid in zip(sources, scored["networks"], scored["cuboid"]):
        fit = fitter.fit(source.sample.noisy)
        truth = Truth.of_sample(source.sample)
        expected = against_truth(fit.keypoints, fit.ratios, truth, fit.cuboid.fit.camera)
        np.testing.assert_allclose(np.concatenate([cuboid.hull, cuboid.interior]),
                                   np.concatenate([expected.hull, expected.interior]), atol=1e-4)
        assert cuboid.iou3d == pytest.approx(expected.iou3d, abs=1e-4)
        plain = Fitter([model], FitOptions(device="cpu", shape="box")).fit(source.sample.noisy)  # --networks-only
        alone = against_truth(plain.keypoints, plain.ratios, truth)
        np.testing.assert_allclose(np.concatenate([networks.hull, networks.interior]),
                                   np.concatenate([alone.hull, alone.interior]), atol=1e-4)


def test_the_paths_table_prints_no_figure_it_cannot_explain():
    from cuboidtrain.train.evaluate import format_paths, summarise_paths

    keys = summarise_paths({"x": []})["x"]  # every figure, each None: a path without an answer
    figures = {k: 0.5 for k in keys} | {"samples": 4, "failed": 0}
    networks = figures | {"focal_mean_rel": 21.504, "focal_median_rel": 20.0, "within_1sd": None, "within_2sd": None}
    given = figures | {"focal_mean_rel": 0.0, "focal_median_rel": 0.0}
    lines = format_paths({"networks": networks, "cuboid": figures, "cuboid_camera_given": given,
                          "none": keys | {"samples": 4, "failed": 4}})
    table = "\n".join(lines)
    assert "2150.4" not in table and "2000.0" not in table  # the lifted free corners' focal length: meaningless
    rows = {line[2:24].strip(): line[24:] for line in lines[2:] if not line.strip().startswith("n/a")}  # less the legend
    cells = {label: [row[i:i + 20].strip() for i in range(0, 80, 20)] for label, row in rows.items()}
    assert cells["focal length rel %"][0].startswith("n/a") and cells["truth in 1 / 2 sd %"][0].startswith("n/a")
    assert cells["focal length rel %"][2] == "given"
    assert all(cell and cell != "-" for row in cells.values() for cell in row), cells  # every blank says why
    assert all(cell.startswith("n/a") for label, row in cells.items() if label != "answered" for cell in row[3:])


def test_eval_hands_the_candidate_the_input_infer_hands_it_grey_or_binary():
    """eval rebuilds the framed masks from the batch's +-1 input: a grey model's each pixel's covered
    share (what `infer` frames and `Fitter.candidate` reads, half covered counting as the object), a
    binary model's the object. Before, a grey pixel covered exactly half was background to eval."""
    import torch

    from cuboidtrain.fit.masks import levels
    from cuboidtrain.train.evaluate import model_inputs
    from shared.sample import signed

    rng = np.random.default_rng(5)
    coverage = rng.choice([0.0, 0.25, 0.5, 0.75, 1.0], size=(3, 8, 8))
    x1 = torch.from_numpy(signed(levels(coverage, grey=True)))[:, None]
    grey = model_inputs(x1, grey=True)
    np.testing.assert_allclose(grey, coverage, atol=1e-7)
    assert ((grey >= 0.5) == levels(coverage, grey=False)).all() and (coverage == 0.5).any()
    binary = levels(coverage, grey=False)
    assert (model_inputs(torch.from_numpy(signed(binary))[:, None], grey=False) == binary).all()
