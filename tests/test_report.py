"""The report: its experiments on tiny models and spools, and REPORT.md written from them."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from cuboidgen.config import PAPER
from cuboidtrain.models.checkpoint import save_checkpoint
from cuboidtrain.cli import app
from cuboidtrain.train.evaluate import load_batches
from cuboidtrain.experiments.report import NOISE_LEVELS, OCCLUSION_BINS, ReportConfig, generated_batches, run_report, table3
from cuboidtrain.experiments.report_figures import PAPER_TABLE3
from shared.sample import encode
from shared.spool import SpoolWriter
from tests.conftest import build_sample, small_library, tiny_model, train_config

SIZE = 32
runner = CliRunner()


def spool_of(folder: Path, shape: str, count: int, scene=PAPER) -> Path:
    with SpoolWriter(folder, limit=0) as writer:
        for seed in range(count):
            writer.publish(encode(build_sample(seed, shape, size=SIZE, scene=scene)))
    return folder


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    clean = replace(PAPER, occluders=(0, 0), contour_noise=(0.0, 0.0))
    spools = {
        "clean-box": spool_of(root / "clean-box", "box", 4, clean),
        "clean-twobox": spool_of(root / "clean-twobox", "twobox", 4, clean),
        "noisy-box": spool_of(root / "noisy-box", "box", 4),
    }
    ckpts = {s: save_checkpoint(root / f"{s}.pt", tiny_model(s, SIZE, seed=1), train_config(shape=s, size=SIZE), step=7)
             for s in ("box", "twobox")}
    return root, spools, ckpts


def test_generated_sweep_levels_share_poses_and_differ_in_noise(tmp_path):
    library = small_library()
    quiet = replace(PAPER, occluders=(0, 0), contour_noise=(0.0, 0.0))
    loud = replace(quiet, contour_noise=(4.0, 4.0))
    a, params_a = generated_batches(tmp_path / "a", "box", SIZE, quiet, 5, 100, library)
    b, params_b = generated_batches(tmp_path / "b", "box", SIZE, loud, 5, 100, library)
    assert torch.equal(a[0].keypoints, b[0].keypoints)  # the same poses at every level
    assert not torch.equal(a[0].noisy, b[0].noisy)
    assert torch.equal(a[0].noisy, a[0].clean)  # no noise, no occluders: x1 is the clean mask
    assert sorted(p["contour_noise"] for p in params_b.values()) == [4.0 * SIZE / 256] * 5


def by_hand(model, spool: Path, extractor: str) -> float:
    """Table 3's figure computed apart from `evaluate`: each sample of the spool decoded on its own,
    the chain run on its noisy mask alone (one Refiner pass), the keypoints read (T's, or the PDM's
    projection of each heat map's brightest pixel), and the mean corner distance to the truth in numpy."""
    from cuboidtrain.models.settings import DEFAULT_PDM_COMPONENTS
    from shared.sample import decode
    from shared.spool import enumerate_spool, read_sample_bytes

    model.eval()
    distances = []
    with torch.inference_mode():
        for name in enumerate_spool(spool):
            sample = decode(read_sample_bytes(spool, name))
            x1 = torch.from_numpy(np.where(sample.noisy, 1.0, -1.0)).float()[None, None]
            out = model(x1, 1)
            if extractor == "tabulator":
                keypoints = out.tabulated[0].double().numpy()
            else:
                maps = out.heatmaps[0].double().numpy()
                brightest = maps.reshape(len(maps), -1).argmax(1)
                keypoints = np.stack([brightest % SIZE, brightest // SIZE], 1).astype(float)
                keypoints = model.pdm.project(keypoints[None], DEFAULT_PDM_COMPONENTS)[0]
            distances.append(np.hypot(*(keypoints - sample.keypoints).T))
    assert len(distances) == 4
    return float(np.mean(distances))


def test_table3_rows_are_the_mean_corner_error_computed_by_hand(setup):
    _, spools, _ = setup
    model = tiny_model("box", SIZE, seed=2)
    batches, _ = load_batches(spools["clean-box"], "box", SIZE, 32, None)
    rows = table3("box", model, batches, torch.device("cpu"))
    assert [r["configuration"] for r in rows] == list(PAPER_TABLE3)
    assert [r.get("samples") for r in rows] == [4, 4, 4, None, None]
    random = tiny_model("box", SIZE, seed=0, sigma=model.sigma)  # row 0: the same architecture, seed 0
    assert rows[0]["mean_px_error"] == pytest.approx(by_hand(random, spools["clean-box"], "tabulator"), rel=1e-6)
    assert rows[1]["mean_px_error"] == pytest.approx(by_hand(model, spools["clean-box"], "tabulator"), rel=1e-6)
    assert model.pdm is not None  # row 2 gave it the generated PDM
    assert rows[2]["mean_px_error"] == pytest.approx(by_hand(model, spools["clean-box"], "pdm"), rel=1e-6)
    assert rows[0]["mean_px_error"] != pytest.approx(rows[1]["mean_px_error"], rel=1e-6)  # two different models
    assert "mean_px_error" not in rows[3] and "mean_px_error" not in rows[4]  # not given: not trained


def test_run_report_measures_every_experiment(setup):
    _, spools, ckpts = setup
    config = ReportConfig(checkpoints=(str(ckpts["box"]), str(ckpts["twobox"])),
                          clean_spools=(str(spools["clean-box"]), str(spools["clean-twobox"])),
                          noisy_spools=(str(spools["noisy-box"]),), e2e=(str(ckpts["twobox"]),),
                          samples=3, sweep_samples=3)
    results = run_report(config)
    box, twobox = results.shapes["box"], results.shapes["twobox"]
    assert box["clean_spool"] == str(spools["clean-box"]) and twobox["clean_spool"] == str(spools["clean-twobox"])
    assert box["table3"][1]["samples"] == 3
    assert twobox["table3"][4]["mean_px_error"] == pytest.approx(twobox["table3"][1]["mean_px_error"])  # same file
    assert [r["contour_noise_256px"] for r in box["noise"]] == list(NOISE_LEVELS)
    assert sum(r["samples"] for r in box["occlusion"]) == 6 and len(box["occlusion"]) == len(OCCLUSION_BINS) - 1
    assert set(box["extractors"]) == {"clean", "noisy"} and set(twobox["extractors"]) == {"clean"}
    assert [r["refine_steps"] for r in box["refinement"]] == [0, 1, 2, 3, "auto"] and "refinement" not in twobox
    selection = results.shape_selection
    assert selection["samples"] == 6 and sum(map(sum, (r.values() for r in selection["confusion"].values()))) == 6
    assert selection["accuracy"] == pytest.approx((selection["confusion"]["box"]["box"]
                                                   + selection["confusion"]["twobox"]["twobox"]) / 6)
    assert results.models["box"]["trained"]["step"] == 7
    assert 1 <= results.models["box"]["pdm"]["components"] <= 16
    assert list(results.to_dict()) == ["config", "models", "shapes", "shape_selection"]  # report.json's keys, in order
    assert results.config == config and results.to_dict()["config"] == config.__dict__


def test_cli_writes_the_report_its_json_and_plots(setup):
    root, spools, ckpts = setup
    out = root / "out"
    result = runner.invoke(app, ["report", "--checkpoint", str(ckpts["box"]), "--clean-spool", str(spools["clean-box"]),
                                 "--noisy-spool", str(spools["noisy-box"]), "--out", str(out),
                                 "--samples", "2", "--sweep-samples", "2"])
    assert result.exit_code == 0, result.output
    text = (out / "REPORT.md").read_text()
    for heading in ("## Table 3", "## Figure 14", "## Error against occlusion", "## Iterative refinement",
                    "## Keypoint extractors"):
        assert heading in text
    assert "## Shape selection" not in text  # one model: nothing to choose between
    results = json.loads((out / "report.json").read_text())
    assert list(results) == ["config", "models", "shapes"]  # one model: no shape selection
    table = results["shapes"]["box"]["table3"]
    assert f"| random weights | 17.9 | {table[0]['mean_px_error']:.2f}" in text  # the numbers are the JSON's
    for name in ("noise", "occlusion", "refinement", "extractors"):
        image = cv2.imread(str(out / f"{name}.png"))
        assert image is not None and image.shape[0] > 300 and np.ptp(image) > 100
        assert f"({name}.png)" in text


@pytest.mark.parametrize("extra, message", [
    (["--samples", "0"], "--samples 0: expected a positive number"),
    (["--e2e", "{twobox}"], "--e2e {twobox}: a twobox model, but no --checkpoint of that shape"),
    (["--finetune", "{box64}"], "a 64 px model with sigma 1.0, expected 32 px"),
    (["--clean-spool", "{root}/nowhere"], "nowhere"),
    (["--checkpoint", "{box}"], "a second 'box' model"),
])
def test_cli_bad_options_are_one_line_errors(setup, extra, message):
    root, spools, ckpts = setup
    args = ["report", "--checkpoint", str(ckpts["box"]), "--clean-spool", str(spools["clean-box"]), "--out", str(root / "x")]
    if not (root / "box64.pt").exists():
        save_checkpoint(root / "box64.pt", tiny_model("box", 64), train_config(shape="box", size=64), step=1)
    names = {"root": root, "box": ckpts["box"], "twobox": ckpts["twobox"], "box64": root / "box64.pt"}
    message = message.format(**names)
    result = runner.invoke(app, args + [a.format(**names) for a in extra])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], result.output
