"""infer --photo (issue 38, Must have 6): a photo's EXIF focal length sets the mask's camera, loosely;
a photo without it changes nothing and says so once; --focal-px wins."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational
from typer.testing import CliRunner

from cuboidgen.config import STREET
from cuboidtrain.cli import app
from cuboidtrain.fit.exif import PhotoCamera, read_photo_camera
from cuboidtrain.geometry.accuracy import Truth
from tests.conftest import build_sample

SIZE = 256


def write_photo(path, size=(400, 300), orientation=None, **fields) -> str:
    """A JPEG of `size` (W, H) whose EXIF sub-IFD holds `fields` (ExifTags.Base names)."""
    exif = Image.Exif()
    for name, value in fields.items():
        exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base[name]] = value
    if orientation is not None:
        exif[ExifTags.Base.Orientation] = orientation
    Image.new("RGB", size, (90, 120, 150)).save(path, exif=exif)
    return str(path)


def test_a_35_mm_equivalent_focal_length_is_taken_along_the_diagonal(tmp_path):
    camera = read_photo_camera(write_photo(tmp_path / "p.jpg", FocalLengthIn35mmFilm=28))
    assert camera.size == (400, 300)
    assert camera.focal_px == pytest.approx(28 * 500 / math.hypot(36, 24))  # 500 px across the diagonal


@pytest.mark.parametrize("unit, per_unit", [(2, 2540), (3, 1000), (4, 100)])  # 100 px a mm: in inches, cm, mm
def test_a_focal_length_in_mm_and_the_focal_plane_resolution_give_px(tmp_path, unit, per_unit):
    path = write_photo(tmp_path / "p.jpg", FocalLength=IFDRational(42, 10),
                       FocalPlaneXResolution=IFDRational(per_unit, 1), FocalPlaneResolutionUnit=unit)
    assert read_photo_camera(path).focal_px == pytest.approx(420.0)


def test_a_photo_stored_on_its_side_is_measured_as_seen_and_one_without_exif_says_none(tmp_path):
    turned = read_photo_camera(write_photo(tmp_path / "t.jpg", orientation=6, FocalLengthIn35mmFilm=28))
    assert turned.size == (300, 400)
    assert read_photo_camera(write_photo(tmp_path / "bare.jpg")) is None


def test_a_resized_whole_frame_scales_the_focal_length_and_a_crop_leaves_the_principal_point_free():
    photo = PhotoCamera("p.jpg", 3000.0, (4000, 3000), "")
    resized = photo.in_frame((300, 400))  # (H, W): the photo at a tenth
    assert resized.focal_px == pytest.approx(300.0) and resized.principal_px == (199.5, 149.5)
    assert resized.exif == ("focal_px", "principal_px") and not resized.focal_held
    crop = photo.in_frame((256, 256))
    assert crop.focal_px == 3000.0 and crop.principal_px is None and crop.exif == ("focal_px",)
    assert resized.stiffness < 20 and resized.principal_stiffness < 1  # loose priors, not held (1000)


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """Two noisy 256 px street masks, and photos of their frame carrying each true focal length in
    EXIF (a 35 mm equivalent rounded to whole mm, as cameras write it), and two without EXIF."""
    folder = tmp_path_factory.mktemp("street")
    masks, photos, bare, truths = [], [], [], []
    for seed in range(2):
        sample = build_sample(seed, "box", size=SIZE, scene=STREET)
        truth = Truth.of_sample(sample)
        masks.append(str(folder / f"m{seed}.png"))
        cv2.imwrite(masks[-1], sample.noisy.astype(np.uint8) * 255)
        equivalent = round(truth.known_camera().focal_px * math.hypot(36, 24) / math.hypot(SIZE, SIZE))
        photos.append(write_photo(folder / f"p{seed}.jpg", (SIZE, SIZE), FocalLengthIn35mmFilm=equivalent))
        bare.append(write_photo(folder / f"b{seed}.jpg", (SIZE, SIZE)))
        truths.append(truth)
    return masks, photos, bare, truths


def infer(tmp_path, name, *args) -> tuple[list[dict], str]:
    out = tmp_path / f"{name}.json"
    result = CliRunner().invoke(app, ["infer", "--device", "cpu", "--json", str(out), *args])
    assert result.exit_code == 0, result.output
    return json.loads(out.read_text()), result.output


def photo_args(photos) -> list[str]:
    return [arg for photo in photos for arg in ("--photo", photo)]


def test_the_exif_focal_length_sets_the_camera_loosely_and_the_record_says_so(street, tmp_path):
    masks, photos, _, truths = street
    records, _ = infer(tmp_path, "exif", *masks, *photo_args(photos))
    for record, truth, photo in zip(records, truths, photos):
        cuboid = record["cuboid"]
        assert cuboid["intrinsics"] == {"focal_px": "exif", "principal_px": "exif"}
        exif_focal = read_photo_camera(photo).focal_px
        assert exif_focal == pytest.approx(truth.known_camera().focal_px, rel=0.05)  # whole mm
        assert cuboid["focal_px"] == pytest.approx(exif_focal, rel=0.3)  # a prior: near it, not held to it
        assert cuboid["focal_sd_px"] is not None  # not given: it keeps an error bar of its own


def test_photos_without_exif_change_nothing_and_say_so_in_one_line(street, tmp_path):
    masks, _, bare, _ = street
    plain, _ = infer(tmp_path, "plain", *masks)
    records, said = infer(tmp_path, "bare", *masks, *photo_args(bare))
    assert records == plain
    lines = [line for line in said.splitlines() if "EXIF" in line]
    assert len(lines) == 1 and "2 of 2 photos" in lines[0], said


def test_focal_px_overrides_the_exif_focal_length(street, tmp_path):
    masks, photos, _, _ = street
    records, _ = infer(tmp_path, "both", *masks, *photo_args(photos), "--focal-px", "321")
    for record in records:
        assert record["cuboid"]["intrinsics"] == {"focal_px": "given", "principal_px": "exif"}
        assert record["cuboid"]["focal_px"] == pytest.approx(321.0, rel=1e-3)


@pytest.mark.parametrize("extra, says", [
    ((), "--photo given 1 times for 2 inputs"),
    (("--networks-only",), "--photo with --networks-only"),
])
def test_photos_that_cannot_be_used_are_one_line_errors(street, extra, says):
    masks, photos, _, _ = street
    result = CliRunner().invoke(app, ["infer", "--device", "cpu", *masks, "--photo", photos[0], *extra])
    assert result.exit_code == 2 and says in result.output and len(result.output.strip().splitlines()) == 1, \
        result.output
