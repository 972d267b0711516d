"""Generated masks for anyone (issue 30, Must have 5): `cuboidgen masks SPOOL OUT_DIR` writes each sample's
input mask as a PNG and its truth as JSON, so that `cuboidtrain infer OUT_DIR` runs on them as written.
"""
from __future__ import annotations

import json

import cv2
import numpy as np
from typer.testing import CliRunner

from cuboidgen.cli import app as gen_app
from cuboidtrain.cli import app as train_app
from shared.camera import Intrinsics
from shared.sample import decode
from shared.shapes import get_shape
from shared.spool import enumerate_spool, read_sample_bytes
from tests.conftest import fill_spool

runner = CliRunner()


def test_masks_writes_each_sample_as_a_png_and_its_truth(tmp_path):
    spool, out = tmp_path / "spool", tmp_path / "masks"
    spool.mkdir()
    fill_spool(spool, 3, shape="twobox", size=64)
    result = runner.invoke(gen_app, ["masks", str(spool), str(out)])
    assert result.exit_code == 0, result.output
    assert result.output.startswith(f"wrote 3 masks and their truth to {out}")
    assert sorted(p.name for p in out.iterdir()) == [f"0000{k}.{e}" for k in range(3) for e in ("json", "png")]
    for k, name in enumerate(enumerate_spool(spool)):
        sample = decode(read_sample_bytes(spool, name))
        png = cv2.imread(str(out / f"0000{k}.png"), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint8 and np.array_equal(png > 0, sample.noisy) and set(np.unique(png)) <= {0, 255}
        truth = json.loads((out / f"0000{k}.json").read_text())
        camera = Intrinsics.from_params(sample.params)
        assert truth["mask"] == f"0000{k}.png" and truth["sample"] == name and truth["shape"] == "twobox"
        assert np.array_equal(truth["keypoints"], sample.keypoints) and truth["ratios"] == sample.ratios
        assert truth["keypoint_names"] == list(get_shape("twobox").keypoint_names)
        assert truth["camera"] == {"focal_px": camera.focal, "principal_px": list(camera.principal)}


def test_infer_runs_on_the_written_masks_as_they_are(tmp_path):
    spool, out = tmp_path / "spool", tmp_path / "masks"
    spool.mkdir()
    fill_spool(spool, 4, size=64)
    assert runner.invoke(gen_app, ["masks", str(spool), str(out), "--count", "2", "--clean"]).exit_code == 0
    assert sorted(p.name for p in out.glob("*.png")) == ["00000.png", "00001.png"]
    first = decode(read_sample_bytes(spool, enumerate_spool(spool)[0]))
    assert np.array_equal(cv2.imread(str(out / "00000.png"), cv2.IMREAD_GRAYSCALE) > 0, first.clean)
    result = runner.invoke(train_app, ["infer", str(out), "--json", "-", "--device", "cpu"])
    records = json.loads(result.stdout)
    assert result.exit_code == 0 and [r["input"] for r in records] == [str(out / "00000.png"), str(out / "00001.png")]
    assert all(r["error"] is None for r in records)  # the JSON files beside them are not inputs


def test_an_empty_or_missing_spool_and_a_bad_count_are_one_line_errors(tmp_path):
    (empty := tmp_path / "empty").mkdir()
    for args, message in (([str(tmp_path / "nowhere"), str(tmp_path / "o")], "spool"),
                          ([str(empty), str(tmp_path / "o")], "no decodable sample"),
                          ([str(empty), str(tmp_path / "o"), "--count", "0"], "--count 0: expected at least 1")):
        result = runner.invoke(gen_app, ["masks", *args])
        assert result.exit_code == 2 and result.output.startswith("error: ") and message in result.output
        assert result.output.count("\n") == 1
