"""The cuboidgen command line through typer's CliRunner: real runs, JSON, pictures and one-line errors."""
import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cuboidgen.cli import app
from tests.conftest import build_sample, fill_spool

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


def cells(image, rows: int, columns: int):
    """The picture cut into a rows x columns grid of equal cells (the figure's panels), row by row."""
    height, width = image.shape[0] // rows, image.shape[1] // columns
    return [image[r * height:(r + 1) * height, c * width:(c + 1) * width] for r in range(rows) for c in range(columns)]


def largest_blob(mask):
    """The bounding box (x, y, w, h) of the largest 8-connected component of `mask`."""
    _, _, stats, _ = cv2.connectedComponentsWithStats(mask.astype("uint8"))
    return tuple(stats[1 + stats[1:, cv2.CC_STAT_AREA].argmax(), :4])


def shown_mask(cell, dark: int, size: int):
    """The mask a panel shows: the panel's image (the largest dark region: the mask's background
    frames the building) read back at the sample's size, light pixels True."""
    gray = cv2.cvtColor(cell, cv2.COLOR_BGR2GRAY)
    x, y, w, h = largest_blob(gray < dark)
    return cv2.resize(gray[y:y + h, x:x + w], (size, size), interpolation=cv2.INTER_AREA) > 128


def coloured(cell, bgr) -> int:
    """Pixels of about this colour (the wireframe's green, the keypoints' red)."""
    return int((abs(cell.astype(int) - bgr).max(axis=-1) < 40).sum())


GREEN, RED = (44, 160, 44), (40, 39, 214)  # preview.EDGE_COLOUR, preview.INDEX_COLOUR in BGR


def test_preview_draws_each_sample_s_input_beside_its_wireframe(tmp_path, library):
    """6 samples at 4 a row: a 2 x 8 grid of panels (16.8 x 4.6 in at 110 dpi), sample k's panels k-th,
    its noisy input on the left and its clean silhouette under a green wireframe with red keypoints
    on the right, as the samples hold them; the last row's two unused pairs left blank."""
    fill_spool(tmp_path / "spool", 6, shape="twobox", library=library)  # seeds 0..5, oldest first
    samples = [build_sample(seed, "twobox", library=library) for seed in range(6)]
    out = tmp_path / "grid.png"
    result = runner.invoke(app, ["preview", str(tmp_path / "spool"), "--out", str(out), "--count", "6"])
    assert result.exit_code == 0, result.output
    image = cv2.imread(str(out))
    assert image is not None and image.shape == (round(2 * 2.3 * 110), round(4 * 4.2 * 110), 3)
    panels = cells(image, 2, 8)
    for k, sample in enumerate(samples):
        left, right = panels[2 * k], panels[2 * k + 1]
        assert (shown_mask(left, 60, sample.size) == sample.noisy).mean() > 0.99, k  # the input, pixel for pixel
        assert (shown_mask(right, 100, sample.size) == sample.clean).mean() > 0.97, k  # under the wireframe
        assert coloured(left, GREEN) == 0 and coloured(left, RED) == 0
        assert coloured(right, GREEN) > 500 and coloured(right, RED) > 200, k  # its edges and keypoints
    assert all(panel.min() >= 250 for panel in panels[12:])  # nothing drawn past the sixth sample


def test_occluders_preview_tiles_every_cutout(tmp_path):
    """The built-in library: 80 cutouts, 10 a row, each cell holds one (more ink than its label).
    A folder of three: one row of ten cells, each cutout in its own cell with its proportions, the rest blank."""
    from cuboidgen.occluders import OccluderLibrary

    out = tmp_path / "occ.png"
    assert runner.invoke(app, ["occluders", "preview", "--out", str(out)]).exit_code == 0
    image, count = cv2.imread(str(out)), len(OccluderLibrary.load(None))
    rows = -(-count // 10)
    assert count == 80 and image is not None and image.shape == (round(1.5 * rows * 100), 1300, 3)
    inked = [cv2.connectedComponentsWithStats((cv2.cvtColor(c, cv2.COLOR_BGR2GRAY) < 128).astype("uint8"))[2][1:, 4].max(
        initial=0) for c in cells(image, rows, 10)]
    assert min(inked) >= 150, inked  # a cutout in every cell, not only a label

    folder = tmp_path / "cutouts"
    folder.mkdir()
    shapes = {"a_square": (40, 40), "b_tall": (60, 10), "c_wide": (10, 60)}  # (h, w)
    for name, (h, w) in shapes.items():
        cv2.imwrite(str(folder / f"{name}.png"), np.full((h, w), 255, np.uint8))
    out = tmp_path / "three.png"
    result = runner.invoke(app, ["occluders", "preview", "--occluders", str(folder), "--out", str(out)])
    assert result.exit_code == 0, result.output
    image = cv2.imread(str(out))
    assert image is not None and image.shape == (150, 1300, 3)
    grid = cells(image, 1, 10)
    for cell, (h, w) in zip(grid, shapes.values()):
        _, _, bw, bh = largest_blob(cv2.cvtColor(cell, cv2.COLOR_BGR2GRAY) < 128)
        assert bh / bw == pytest.approx(h / w, rel=0.2) and max(bw, bh) > 30, (bw, bh, h, w)
    assert all(cell[30:].min() >= 250 for cell in grid[3:])  # below the figure's title: blank


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
