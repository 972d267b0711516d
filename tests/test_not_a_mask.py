"""What is not a binary mask is said (issue 30, Must have 1): a photo or a greyscale image is refused in
one line, `--threshold T` and `--invert` say what the object is, and no Python warning reaches the user.

Through the command, with the shipped models, as a user runs it. A binary mask is read exactly as
before: `legacy_mask` is the rule `to_mask` had, and every valid binary mask gives its pixels.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cuboidtrain.cli import app
from cuboidtrain.fit.masks import MAX_BETWEEN, load_mask, to_mask
from shared.errors import UsageError
from tests.conftest import build_sample

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()


def legacy_mask(image: np.ndarray) -> np.ndarray:
    """`to_mask` before issue 30, without a label id: a varying alpha at half its scale, else the
    grey (colour: its brightest channel) above half its maximum."""
    image = np.asarray(image)
    if image.dtype == bool:
        image = image.astype(np.uint8)
    if image.ndim == 3 and image.shape[2] == 4 and image[..., 3].min() != image[..., 3].max():
        top = np.iinfo(image.dtype).max if image.dtype.kind in "ui" else 1.0
        return image[..., 3] > top / 2
    grey = image if image.ndim == 2 else image[..., :3].max(axis=2)
    return grey > grey.max() / 2 if grey.max() > 0 else np.zeros(grey.shape, bool)


def building(shape=(120, 160)) -> np.ndarray:
    """A two-winged building standing inside the frame, as a bool mask."""
    mask = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(mask, np.array([[30, 40], [80, 25], [82, 100], [32, 104]], np.int32), 1)
    cv2.fillConvexPoly(mask, np.array([[80, 25], [130, 38], [128, 96], [82, 100]], np.int32), 1)
    return mask.astype(bool)


def photo(shape=(120, 160)) -> np.ndarray:
    """A photograph's worth of grey levels: smooth shading and texture, BGR."""
    rng = np.random.default_rng(3)
    ys, xs = np.mgrid[: shape[0], : shape[1]]
    shade = 60 + 120 * xs / shape[1] + 40 * np.sin(ys / 9.0)
    texture = cv2.GaussianBlur(rng.normal(0, 40, shape), (0, 0), 2)
    grey = np.clip(shade + texture, 0, 255).astype(np.uint8)
    return np.dstack([grey, np.clip(grey * 0.9, 0, 255).astype(np.uint8), grey])


def write(folder: Path, name: str, image: np.ndarray) -> str:
    assert cv2.imwrite(str(folder / name), image)
    return str(folder / name)


def infer(*args: str) -> tuple[int, list[dict] | None, str]:
    result = runner.invoke(app, ["infer", *args, "--device", "cpu", "--json", "-"])
    out = result.stdout.strip()
    return result.exit_code, (json.loads(out) if out.startswith("[") else None), result.output


@pytest.fixture(scope="module")
def binary_fit(tmp_path_factory) -> dict:
    """`building()` as a binary PNG, fitted once: the record each reading of it must give, to the byte."""
    _, [record], _ = infer(write(tmp_path_factory.mktemp("binary"), "binary.png", building().astype(np.uint8) * 255))
    return record


# --- binary masks: as before ---------------------------------------------------------------

@pytest.mark.parametrize("name, encode", [
    ("grey255", lambda m: m.astype(np.uint8) * 255),
    ("grey01", lambda m: m.astype(np.uint8)),
    ("bool", lambda m: m),
    ("sixteen_bit", lambda m: m.astype(np.uint16) * 65535),
    ("signed", lambda m: np.where(m, 1.0, -1.0).astype(np.float32)),
    ("colour_on_black", lambda m: np.where(m[..., None], np.uint8([30, 200, 90]), np.uint8(0))),
    ("two_colours_on_black", lambda m: np.where(m[..., None], np.uint8([0, 0, 255]), np.uint8(0))
     + np.where(np.roll(m, 3, axis=1)[..., None] & m[..., None], np.uint8([255, 0, 0]), np.uint8(0))),
    ("opaque_rgba", lambda m: np.dstack([m.astype(np.uint8) * 255] * 3 + [np.full(m.shape, 255, np.uint8)])),
    ("cutout_rgba", lambda m: np.dstack([np.full((*m.shape, 3), 90, np.uint8), m.astype(np.uint8) * 255])),
])
def test_a_binary_mask_reads_as_it_did(name, encode):
    for mask in (building(), build_sample(4, "twobox", size=96).noisy, build_sample(5, "box", size=64).noisy):
        image = encode(mask)
        assert np.array_equal(to_mask(image), legacy_mask(image)), name
        assert np.array_equal(to_mask(image), mask), name


@pytest.mark.parametrize("quality, scale", [(10, 1.0), (40, 1.0), (90, 1.0), (95, 0.1), (95, 0.25)])
def test_a_jpeg_noisy_or_shrunk_mask_is_still_a_mask_read_as_before(tmp_path, quality, scale):
    mask = cv2.imread(str(ROOT / "examples" / "building.png"), cv2.IMREAD_UNCHANGED)
    mask = cv2.resize(mask, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale != 1 else mask
    path = tmp_path / "m.jpg"
    assert cv2.imwrite(str(path), mask, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert np.array_equal(load_mask(path), legacy_mask(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)))


# --- what is not a mask ---------------------------------------------------------------------

def test_a_photo_is_refused_naming_what_was_found_and_what_is_expected(tmp_path):
    good = write(tmp_path, "good.png", building().astype(np.uint8) * 255)
    code, records, output = infer(write(tmp_path, "photo.jpg", photo()), good)
    assert code == 1 and records[1]["error"] is None
    error = records[0]["error"]
    assert error.startswith(f"{tmp_path}/photo.jpg: not a binary mask: ") and "\n" not in error
    share = int(error.split("not a binary mask: ")[1].split("%")[0])
    assert share > 100 * MAX_BETWEEN and "expected two values" in error and "--threshold T" in error
    assert records[0]["keypoints"] is None


def test_a_greyscale_image_is_cut_where_threshold_says(tmp_path, binary_fit):
    mask = building()
    grey = cv2.cvtColor(photo(), cv2.COLOR_BGR2GRAY) // 2  # a dark textured background, 0 to 127
    grey[mask] += 128  # and a bright textured building
    path = write(tmp_path, "grey.png", grey)
    assert "not a binary mask" in infer(path)[1][0]["error"]
    for threshold in (100, 127.5):
        assert np.array_equal(load_mask(path, threshold=threshold), grey > threshold)
    assert np.array_equal(load_mask(path, threshold=100, invert=True), grey <= 100)
    with pytest.raises(UsageError, match=r"the object \(pixels at or below 127.5 .* drop --invert"):
        load_mask(path, threshold=127.5, invert=True)  # all the background, which covers the border
    code, [by_threshold], _ = infer(path, "--threshold", "127")
    assert code == 0 and by_threshold | {"input": binary_fit["input"]} == binary_fit


def test_a_dark_building_on_white_is_refused_and_read_with_invert(tmp_path, binary_fit):
    mask = building()
    binary = write(tmp_path, "binary.png", mask.astype(np.uint8) * 255)
    dark = write(tmp_path, "dark.png", np.where(mask, 0, 255).astype(np.uint8))
    red = write(tmp_path, "red.png", np.where(mask[..., None], np.uint8([0, 0, 255]), np.uint8(255)))  # BGR
    code, records, _ = infer(dark, red)
    assert code == 1
    assert "dark.png: the object (pixels above 127.5 in its grey levels) covers the whole border" in records[0]["error"]
    assert "red.png: every pixel is the object" in records[1]["error"]
    assert all("pass --invert" in r["error"] for r in records)
    code, inverted, _ = infer(dark, red, "--invert")
    assert code == 0
    for record in inverted:  # the same bool mask: the same fit, to the byte
        assert record | {"input": binary_fit["input"]} == binary_fit
    code, records, _ = infer(binary, "--invert")
    assert code == 1 and "drop --invert" in records[0]["error"]


def test_an_rgb_mask_of_one_colour_on_black_works(tmp_path, binary_fit):
    colour = write(tmp_path, "colour.png", np.where(building()[..., None], np.uint8([40, 180, 250]), np.uint8(0)))
    code, [record], _ = infer(colour)
    assert code == 0 and record | {"input": binary_fit["input"]} == binary_fit


def test_threshold_and_label_id_do_not_combine_and_a_bad_threshold_is_named(tmp_path):
    path = write(tmp_path, "m.png", building().astype(np.uint8) * 255)
    for extra, message in ((["--label-id", "255", "--invert"], "error: --invert with --label-id 255: expected one"),
                           (["--label-id", "255", "--threshold", "3"], "error: --threshold 3 with --label-id 255"),
                           (["--threshold", "-1"], "error: --threshold -1.0: expected a finite number >= 0")):
        result = runner.invoke(app, ["infer", path, *extra])
        assert result.exit_code == 2 and result.output.startswith(message) and result.output.count("\n") == 1


def test_a_label_map_that_is_all_one_label_is_refused():
    with pytest.raises(UsageError, match="every pixel is label 3: no background"):
        to_mask(np.full((20, 30), 3, np.uint8), label_id=3)


# --- no Python warning from any input --------------------------------------------------------

def bad_inputs(folder: Path) -> dict[str, str | None]:
    """Inputs a user may point infer at by mistake, each with the start of its error (None: fitted)."""
    box = np.zeros((60, 80), np.uint8)
    box[10:50, 20:60] = 255
    images = {
        "photo.jpg": (photo(), "not a binary mask"),
        "dark_on_white.png": (255 - box, "the object (pixels above 127.5 in its grey levels) covers the whole border"),
        "red_on_white.png": (np.where(box[..., None] > 0, np.uint8([0, 0, 255]), np.uint8(255)), "every pixel is"),
        "white.png": (np.full((40, 50), 255, np.uint8), "every pixel is the object"),
        "black.png": (np.zeros((40, 50), np.uint8), "empty mask"),
        "one_px.png": (np.full((1, 1), 255, np.uint8), "every pixel is the object"),
        "speck.png": (np.pad(np.full((3, 3), 255, np.uint8), 20), "no component of at least 16 px"),
        "gradient.png": (np.tile(np.linspace(0, 255, 80).astype(np.uint8), (60, 1)), "not a binary mask"),
        "transparent.png": (np.zeros((30, 40, 4), np.uint8), "empty mask"),
        "nan.tiff": (np.where(box > 0, np.nan, 0).astype(np.float32), "1,600 of its pixels are NaN"),
        "line.png": (np.pad(np.full((1, 70), 255, np.uint8), ((30, 29), (5, 5))), None),
        "checker.png": ((np.indices((60, 80)).sum(0) % 2 * 255).astype(np.uint8), None),
        "half.png": (np.hstack([np.full((60, 40), 255, np.uint8), np.zeros((60, 40), np.uint8)]), None),
        "border_but_one_row.png": (np.vstack([np.zeros((1, 80), np.uint8), np.full((59, 80), 255, np.uint8)]), None),
        "sixteen_bit.png": (box.astype(np.uint16) * 257, None),
        "float.tiff": ((box > 0).astype(np.float32), None),
    }
    expected = {}
    for name, (image, error) in images.items():
        expected[write(folder, name, image)] = error
    (folder / "empty.png").write_bytes(b"")
    (folder / "garbage.png").write_bytes(b"not an image at all")
    data = (folder / "white.png").read_bytes()
    (folder / "truncated.png").write_bytes(data[: len(data) // 2])
    for name in ("empty.png", "garbage.png", "truncated.png"):
        expected[str(folder / name)] = "cannot read image"
    return expected


def test_no_input_lets_a_python_warning_reach_the_user(tmp_path):
    expected = bad_inputs(tmp_path)
    out = tmp_path / "out.json"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHONWARNINGS")} | {"PYTHONWARNINGS": "error"}
    done = subprocess.run([sys.executable, "-W", "error", "-c", "from cuboidtrain.cli import main; main()", "infer",
                           *expected, "--device", "cpu", "--json", str(out)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 1, done.stderr[-3000:]  # an error record for the bad ones, the others fitted
    for word in ("Warning", "Traceback", "[ WARN", "warnings.warn"):
        assert word not in done.stderr, done.stderr[-3000:]
    records = {r["input"]: r for r in json.loads(out.read_text())}
    for path, error in expected.items():
        if error is None:
            assert records[path]["error"] is None, records[path]["error"]
        else:
            assert error in (records[path]["error"] or ""), (path, records[path]["error"])
