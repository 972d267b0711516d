"""Inference inputs: reading mask files, picking components, framing for the model.

The framing tests draw polygons with the generator's exact rasteriser (pixel centres
inside the polygon are set) so that where a polygon's vertices go is known exactly.
"""
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.raster import fill_convex
from cuboidtrain.fit.masks import Framing, components, frame, load_mask, warp

# A projected box's silhouette (six hull vertices), in units of its bounding square.
HEXAGON = np.array([[0.12, 0.30], [0.55, 0.08], [0.93, 0.22], [0.95, 0.70], [0.60, 0.97], [0.10, 0.75]])


def draw(points: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    mask = np.zeros(shape, bool)
    fill_convex(mask, points)
    return mask


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return (a & b).sum() / (a | b).sum()


def centroid(mask: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(mask)
    return np.array([xs.mean(), ys.mean()])


# --- framing -------------------------------------------------------------------

# (width, height) of the input, side of the polygon's bounding square and its top-left, px.
INPUTS = [((100, 80), 60, (17.3, 9.6)), ((640, 480), 300, (200.2, 101.7)), ((1200, 900), 700, (350.4, 120.9))]


@pytest.mark.parametrize("size", [64, 256])
@pytest.mark.parametrize("shape, side, corner", INPUTS)
def test_framed_mask_is_the_polygon_drawn_at_model_resolution(shape, side, corner, size):
    polygon = HEXAGON * side + corner  # off-centre, non-integer vertices
    framed, framing = frame(draw(polygon, shape[::-1]), size)
    assert framed.shape == (size, size) and framed.dtype == bool
    model = framing.to_model(polygon)
    assert np.abs(framing.to_input(model) - polygon).max() < 1e-9
    expected = draw(model, (size, size))
    # Upscaling 60 px to 256 magnifies the input's own 1-px stair steps: IoU 0.984 there.
    assert iou(framed, expected) > (0.97 if side < size else 0.99)
    # A half-pixel slip moves the centroid 0.5 px; both rasters' own stair steps move it
    # under 0.07 px (measured), in model px or in input px when upscaling.
    assert np.abs(centroid(framed) - centroid(expected)).max() < 0.1 * max(1.0, framing.scale)


def test_a_half_pixel_slip_would_be_caught():
    polygon = HEXAGON * 700 + (350.4, 120.9)
    framed, framing = frame(draw(polygon, (900, 1200)), 64)
    right = draw(framing.to_model(polygon), (64, 64))
    slipped = draw(framing.to_model(polygon) + 0.5, (64, 64))
    assert (framed ^ right).sum() * 5 < (framed ^ slipped).sum()


# --- grey input: each model pixel's covered share -------------------------------

@pytest.mark.parametrize("shape, side, corner", INPUTS)
def test_a_grey_framing_thresholded_at_half_is_the_binary_one(shape, side, corner):
    mask = draw(HEXAGON * side + corner, shape[::-1])
    binary, framing = frame(mask, 64)
    grey, same = frame(mask, 64, grey=True)
    assert same == framing and grey.dtype == np.float32 and grey.shape == (64, 64)
    assert grey.min() >= 0.0 and grey.max() <= 1.0 and np.array_equal(grey >= 0.5, binary)
    np.testing.assert_allclose(warp(mask, framing, grey=True), grey, atol=1e-5)  # the whole image, not a crop
    # Shrinking, the object's covered area is kept in the grey input to a pixel's share per edge
    # pixel; a binary one rounds each edge pixel to 0 or 1.
    assert abs(grey.sum() - mask.sum() * framing.scale ** 2) < 0.02 * grey.sum()


def test_the_grey_input_keeps_where_an_edge_lies_inside_a_model_pixel():
    # A 256 px half-plane shrunk to 64 px: moving its edge one input pixel (a quarter model pixel)
    # changes the grey input by a quarter pixel's share along the edge; the binary one often not at all.
    framing = Framing(0.25, (-0.375, -0.375), 64, (256, 256))
    sums, changed = [], []
    for edge in range(120, 128):
        mask = np.zeros((256, 256), bool)
        mask[:, :edge] = True
        sums.append(warp(mask, framing, grey=True).sum())
        changed.append(warp(mask, framing).sum())
    steps = np.diff(sums) / 64  # per model row: a quarter of a pixel each input pixel
    # The shrink is a Gaussian then bilinear sampling (`_warp`), not an exact box: each step is
    # 0.20 or 0.30 of a pixel (measured), a quarter on average.
    assert steps.min() > 0.15 and steps.max() < 0.35 and abs(steps.mean() - 0.25) < 0.01
    assert np.count_nonzero(np.diff(changed)) <= 2  # binary: the edge moves a whole pixel every 4 steps


# A model-resolution box silhouette whose extremes are flat edges on pixel boundaries
# (x 5.5 .. 57.5, y 11.5 .. 51.5 at 64 px), centred on the middle pixel 31.5: drawn at
# scale k its bounding box is exactly k times larger, so frame() must recover it.
FLAT = np.array([[5.5, 18.3], [19.7, 11.5], [44.2, 11.5], [57.5, 16.9],
                 [57.5, 43.1], [41.3, 51.5], [17.8, 51.5], [5.5, 46.2]])
FLAT_MARGIN = (1 - 52 / 64) / 2  # the 52-px width fills 64 px less two margins


@pytest.mark.parametrize("k", [2, 3, 5, 16])
def test_model_vertices_go_back_onto_the_input_drawn_at_scale_k(k):
    # Pixel centres: model pixel x covers input [k x, k (x + 1)) - 0.5, so x -> k (x + 0.5) - 0.5.
    corner = np.array([13, 21])
    truth = k * (FLAT + 0.5) - 0.5 + corner
    framed, framing = frame(draw(truth, (64 * k + 40, 64 * k + 30)), 64, margin=FLAT_MARGIN)
    assert framing.scale == pytest.approx(1 / k)
    assert np.abs(framing.to_input(FLAT) - truth).max() < 0.05
    assert iou(framed, draw(FLAT, (64, 64))) > 0.99


@pytest.mark.parametrize("k", [0.5, 3.7, 8.0])
def test_model_vertices_land_near_the_input_at_any_scale(k):
    # Pointed extremes: the bounding box (whole pixels) misjudges the extent by under a
    # pixel, which shifts the framing by as much; keypoints go back through the same
    # framing, so this bounds how far the model's view is from the generator's framing.
    lo, hi = HEXAGON.min(0), HEXAGON.max(0)
    model = (HEXAGON - (lo + hi) / 2) * 0.8 * 64 / (hi - lo).max() + 31.5
    truth = k * (model + 0.5) - 0.5 + (13.0, 21.0)
    _, framing = frame(draw(truth, (int(64 * k) + 40, int(64 * k) + 30)), 64)
    assert abs(framing.scale * k - 1) < 0.02
    assert np.abs(framing.to_input(model) - truth).max() < 1.0


def test_object_touching_the_border_is_framed_whole():
    polygon = HEXAGON * 120 + (-30.0, 50.0)  # runs off the left edge of a 100 x 200 image
    mask = draw(polygon, (200, 100))
    assert mask[:, 0].any()
    framed, framing = frame(mask, 64)
    border = np.concatenate([framed[:4].ravel(), framed[-4:].ravel(), framed[:, :4].ravel(), framed[:, -4:].ravel()])
    assert not border.any()  # the cut edge sits inside the margin, padded with background
    assert framed.sum() == pytest.approx(mask.sum() * framing.scale**2, rel=0.03)
    assert iou(framed, draw(framing.to_model(polygon), (64, 64)) & _inside(framing, mask.shape)) > 0.97


def _inside(framing: Framing, shape: tuple[int, int]) -> np.ndarray:
    """Model pixels whose centres map inside the input image."""
    ys, xs = np.mgrid[0 : framing.size, 0 : framing.size]
    x, y = framing.to_input(np.stack([xs.ravel(), ys.ravel()], axis=1)).T
    return ((x > -0.5) & (x < shape[1] - 0.5) & (y > -0.5) & (y < shape[0] - 0.5)).reshape(xs.shape)


def test_framing_matrix_is_to_model():
    _, framing = frame(draw(HEXAGON * 40 + 5, (60, 50)), 32)
    points = np.array([[0.0, 0.0], [12.5, 7.25], [49.0, 59.0]])
    assert np.allclose(np.c_[points, np.ones(3)] @ framing.matrix.T, framing.to_model(points))
    assert framing.input_shape == (60, 50) and framing.size == 32


def test_a_bad_margin_and_an_empty_mask_are_rejected():
    from cuboidtrain.fit.options import FitOptions

    with pytest.raises(ValueError, match="margin 0.5"):  # checked once, where every fit's options are
        FitOptions(margin=0.5).validate()
    with pytest.raises(ValueError, match="empty"):
        frame(np.zeros((8, 8), bool), 16)


# --- load_mask -----------------------------------------------------------------


@pytest.fixture
def blob() -> np.ndarray:
    return draw(HEXAGON * 40 + (6.3, 4.8), (50, 60))


def write(path: Path, image: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), image)
    return path


@pytest.mark.parametrize("name, encode", [
    ("grey255.png", lambda m: m.astype(np.uint8) * 255),
    ("grey01.png", lambda m: m.astype(np.uint8)),
    ("colour.png", lambda m: np.where(m[..., None], np.uint8([30, 200, 90]), np.uint8(0))),
    ("opaque.png", lambda m: np.dstack([m.astype(np.uint8) * 255] * 3 + [np.full(m.shape, 255, np.uint8)])),
])
def test_load_mask_formats(tmp_path, blob, name, encode):
    assert (load_mask(write(tmp_path / name, encode(blob))) == blob).all()


def test_load_mask_alpha_is_the_object(tmp_path, blob):
    colour = np.random.default_rng(0).integers(0, 256, (*blob.shape, 3), dtype=np.uint8)
    rgba = np.dstack([colour, np.where(blob, 255, 0).astype(np.uint8)])
    assert (load_mask(write(tmp_path / "cutout.png", rgba)) == blob).all()


def test_load_mask_tolerates_jpeg_noise(tmp_path, blob):
    path = tmp_path / "noisy.jpg"
    assert cv2.imwrite(str(path), blob.astype(np.uint8) * 255, [cv2.IMWRITE_JPEG_QUALITY, 40])
    assert len(np.unique(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))) > 2  # really noisy
    assert iou(load_mask(path), blob) > 0.98


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_load_mask_label_map(tmp_path, blob, dtype):
    labels = np.zeros(blob.shape, dtype)
    labels[:, :20], labels[blob] = 7, 11
    path = write(tmp_path / "labels.png", labels)
    assert (load_mask(path, label_id=11) == blob).all()
    with pytest.raises(ValueError, match=r"labels\.png: label 26 not found in the label map \(labels present: 0, 7, 11\)"):
        load_mask(path, label_id=26)


def test_load_mask_errors_name_the_path(tmp_path, blob):
    (garbage := tmp_path / "garbage.png").write_bytes(b"not an image")
    for path in (garbage, tmp_path / "missing.png"):
        with pytest.raises(ValueError, match=f"{path.name}: cannot read image") as error:
            load_mask(path)
        assert "\n" not in str(error.value)
    with pytest.raises(ValueError, match="black.png: empty mask: no object pixels"):
        load_mask(write(tmp_path / "black.png", np.zeros((8, 8), np.uint8)))
    with pytest.raises(ValueError, match="rgb.png: a label id needs a single-channel label map"):
        load_mask(write(tmp_path / "rgb.png", np.dstack([blob.astype(np.uint8) * 255] * 3)), label_id=1)


def jpeg_declaring(width: int, height: int, icc_bytes: int = 0, progressive: bool = False) -> bytes:
    """A tiny JPEG whose frame header claims width x height, after an ICC profile of `icc_bytes` in
    APP2 segments (at most 65533 bytes each, as real profiles are split), and some fill bytes."""
    flags = [cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if progressive else []
    data = bytearray(cv2.imencode(".jpg", np.pad(np.full((4, 4), 255, np.uint8), 2), flags)[1].tobytes())  # a mask
    position = 2
    while not (0xC0 <= data[position + 1] <= 0xC2):  # baseline or progressive frame header
        position += 2 + int.from_bytes(data[position + 2 : position + 4], "big")
    data[position + 5 : position + 9] = height.to_bytes(2, "big") + width.to_bytes(2, "big")
    profile = bytearray()
    while icc_bytes > 0:
        chunk = min(icc_bytes, 65533)
        profile += b"\xff\xe2" + (chunk + 2).to_bytes(2, "big") + b"ICC_PROFILE\x00" + bytes(chunk - 12)
        icc_bytes -= chunk
    return bytes(data[:2] + profile + b"\xff\xff" + data[2:])  # 0xFF fill before the next marker


@pytest.mark.parametrize("icc_bytes", [0, 200_000, 3_000_000])
@pytest.mark.parametrize("progressive", [False, True])
def test_a_huge_jpeg_is_refused_from_its_header_wherever_it_lies(tmp_path, monkeypatch, icc_bytes, progressive):
    path = tmp_path / "huge.jpg"
    path.write_bytes(jpeg_declaring(12_000, 12_000, icc_bytes, progressive))

    def no_decoding(*args, **kwargs):
        raise AssertionError("decoded before its size was checked")
    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    with pytest.raises(ValueError, match=r"^.*huge\.jpg: image of 12000 x 12000 px is too large") as error:
        load_mask(path)
    assert "\n" not in str(error.value)


def test_a_jpeg_behind_a_large_profile_still_reads_and_a_headerless_one_is_refused_unread(tmp_path, monkeypatch):
    path = tmp_path / "small.jpg"
    path.write_bytes(jpeg_declaring(8, 8, icc_bytes=200_000))
    assert load_mask(path).shape == (8, 8)
    data = path.read_bytes()
    frame_header = data.index(b"\xff\xc0")
    (broken := tmp_path / "broken.jpg").write_bytes(data[:frame_header] + b"\xff\xda\x00\x02" + bytes(16))
    monkeypatch.setattr(cv2, "imdecode", lambda *a, **k: pytest.fail("decoded a JPEG whose size is unknown"))
    with pytest.raises(ValueError, match=r"broken\.jpg: cannot read image \(a JPEG without a frame header"):
        load_mask(broken)


# --- components ----------------------------------------------------------------


def test_components_largest_and_all():
    mask = np.zeros((40, 40), bool)
    mask[2:12, 2:12] = True  # 100 px
    mask[12:17, 12:17] = True  # 25 px, touching the first only at a corner: joined (8-connected)
    mask[25:35, 20:26] = True  # 60 px
    mask[30:33, 2:7] = True  # 15 px
    mask[38, 38] = True  # 1 px
    (largest,) = components(mask)
    assert largest.sum() == 125 and largest[2, 2] and largest[16, 16]
    found = components(mask, all_components=True)
    assert [c.sum() for c in found] == [125, 60]
    assert [c.sum() for c in components(mask, all_components=True, min_pixels=1)] == [125, 60, 15, 1]
    assert components(np.zeros((4, 4), bool)) == []


def test_the_silhouette_of_a_building_cut_in_pieces_is_all_its_pieces():
    """An occluder (here a pole, a 3 px column) cuts the building in two: both pieces are it.
    A speck under 1% of the largest piece's area (segmentation noise) is not."""
    from cuboidtrain.fit.masks import PIECE_SHARE, silhouette

    mask = np.zeros((120, 200), bool)
    mask[20:100, 10:90] = True  # 6,400 px
    mask[20:100, 93:150] = True  # 4,560 px, beyond the pole
    mask[110, 190:195] = True  # 5 px: under 16 px, never a piece
    mask[2:6, 170:180] = True  # 40 px: 0.6% of the largest
    building = silhouette(mask)
    assert building.sum() == 6400 + 4560 and building[50, 20] and building[50, 140] and not building[3, 175]
    assert silhouette(mask, min_share=0.005).sum() == 6400 + 4560 + 40  # over the share: a piece too
    assert 40 < PIECE_SHARE * 6400  # the default drops it, as asserted above
    framed, _ = frame(building, 64)
    ys, xs = np.nonzero(framed)
    assert xs.max() - xs.min() + 1 == pytest.approx(64 * 0.8, abs=1)  # framed whole: both pieces, margins kept
    assert silhouette(np.zeros((8, 8), bool)) is None
