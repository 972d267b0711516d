"""The cuboidgen command line through typer's CliRunner: real runs, JSON, pictures and one-line errors."""
import json

import cv2
import pytest
from typer.testing import CliRunner

from cuboidgen.cli import app
from tests.conftest import fill_spool

runner = CliRunner()


def test_run_then_inspect_json(tmp_path):
    spool = tmp_path / "spool"
    result = runner.invoke(app, ["run", "--spool", str(spool), "--limit", "8", "--max-samples", "12", "--workers", "1",
                                 "--size", "32", "--shape", "mix", "--seed", "3", "--scene", "street", "--no-dashboard"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["inspect", str(spool), "--json"])
    report = json.loads(result.stdout)
    assert result.exit_code == 0
    assert {"samples", "files", "bytes", "corrupt", "shapes", "size", "oldest", "newest"} <= set(report)
    assert 8 <= report["samples"] <= 12 and report["corrupt"] == 0 and report["size"] == 32
    assert set(report["shapes"]) <= {"box", "twobox"} and report["scenes"] == {"street": report["samples"]}


def test_inspect_counts_corrupt_and_foreign_files(tmp_path, library):
    fill_spool(tmp_path, 3, library=library)
    (tmp_path / "9999999999999999999-x-1-ab-000000001.cub").write_bytes(b"garbage")
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / ".gitkeep").write_text("")
    report = json.loads(runner.invoke(app, ["inspect", str(tmp_path), "--json"]).stdout)
    assert report["samples"] == 3 and report["corrupt"] == 1 and report["foreign"] == 1


def test_preview_writes_a_picture(tmp_path, library):
    fill_spool(tmp_path / "spool", 6, shape="twobox", library=library)
    out = tmp_path / "grid.png"
    result = runner.invoke(app, ["preview", str(tmp_path / "spool"), "--out", str(out), "--count", "6"])
    assert result.exit_code == 0, result.output
    image = cv2.imread(str(out))
    assert image is not None and image.shape[0] > 100 and image.shape[1] > 400


def test_occluders_preview_writes_a_picture(tmp_path):
    out = tmp_path / "occ.png"
    assert runner.invoke(app, ["occluders", "preview", "--out", str(out)]).exit_code == 0
    assert cv2.imread(str(out)) is not None


def test_scenes_lists_and_prints_presets():
    assert "street" in runner.invoke(app, ["scenes"]).stdout
    preset = json.loads(runner.invoke(app, ["scenes", "street"]).stdout)
    assert preset["name"] == "street" and preset["eye_height"] == [1.4, 1.8]


@pytest.mark.parametrize("args, message", [
    (["run", "--limit", "-1"], "--limit -1"),
    (["run", "--size", "4"], "--size 4"),
    (["run", "--scene", "moon"], "scene 'moon'"),
    (["run", "--workers", "0"], "--workers 0"),
    (["run", "--occluders", "/nonexistent"], "no such folder"),
    (["inspect", "/nonexistent"], "no such folder"),
    (["preview", "/nonexistent"], "no such folder"),
    (["scenes", "moon"], "expected one of"),
])
def test_bad_values_are_one_line_errors(args, message, tmp_path):
    if args[0] == "run":
        args = args + ["--spool", str(tmp_path / "s"), "--max-samples", "1", "--no-dashboard"]
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], result.output


def test_empty_spool_preview_is_a_clear_error(tmp_path):
    result = runner.invoke(app, ["preview", str(tmp_path)])
    assert result.exit_code == 2 and "no decodable sample" in result.output


def test_occluders_extract_reports_counts(tmp_path):
    import numpy as np

    city = tmp_path / "cs" / "gtFine" / "val" / "bonn"
    city.mkdir(parents=True)
    labels = np.zeros((40, 60), np.uint8)
    labels[10:30, 10:30] = 26  # one car
    instances = np.where(labels == 26, 26000, 0).astype(np.uint16)
    cv2.imwrite(str(city / "bonn_000000_000001_gtFine_labelIds.png"), labels)
    cv2.imwrite(str(city / "bonn_000000_000001_gtFine_instanceIds.png"), instances)
    result = runner.invoke(app, ["occluders", "extract", "--cityscapes", str(tmp_path / "cs"), "--out",
                                 str(tmp_path / "out"), "--min-pixels", "50"])
    assert result.exit_code == 0, result.output
    assert "car: 1" in result.stdout and len(list((tmp_path / "out").glob("*.png"))) == 1


def test_cuboidtrain_prints_help():
    from cuboidtrain.cli import app as train_app

    assert "Refiner" in runner.invoke(train_app, ["--help"]).stdout


@pytest.mark.parametrize("program, args, message", [
    ("cuboidgen", ["run", "--shape", "cube"], "'cube' is not one of 'box', 'twobox', 'mix'"),
    ("cuboidgen", ["occluders", "extract", "--min-pixels", "many"], "valid integer"),
    ("cuboidtrain", ["run", "--phase", "3"], "'3' is not one of '1', '2', 'e2e', 'finetune'"),
])
def test_option_errors_give_the_message_without_pydantics_prefix(program, args, message):
    from cuboidtrain.cli import app as train_app

    result = runner.invoke({"cuboidgen": app, "cuboidtrain": train_app}[program], args)
    assert result.exit_code == 2
    text = " ".join(result.output.replace("│", " ").split())  # the error box's lines, joined
    assert message in text and "Value error" not in text, result.output
