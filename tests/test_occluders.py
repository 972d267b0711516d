"""Tests for cuboidgen.occluders: builtin drawing, PNG loading and Cityscapes extraction."""
import logging

import cv2
import numpy as np
import pytest

from cuboidgen.occluders import DEFAULT_CLASSES, KINDS, OccluderLibrary, extract_cityscapes


@pytest.fixture(scope="module")
def lib():
    return OccluderLibrary.builtin(variants_per_kind=12, seed=3)


def _by_kind(lib, kind):
    return [m for m, n in zip(lib.masks, lib.names) if n == kind]


def _runs(row):
    """Number of separate foreground runs in a 1-D 0/1 array."""
    return int(np.count_nonzero(np.diff(np.concatenate([[0], row, [0]])) == 1))


# ---------------------------------------------------------------- builtin

def test_builtin_is_deterministic_per_seed(lib):
    again = OccluderLibrary.builtin(variants_per_kind=12, seed=3)
    assert again.names == lib.names
    assert all(np.array_equal(a, b) for a, b in zip(again.masks, lib.masks))
    other = OccluderLibrary.builtin(variants_per_kind=12, seed=4)
    assert any(a.shape != b.shape or not np.array_equal(a, b) for a, b in zip(other.masks, lib.masks))


def test_builtin_counts_kinds_and_order(lib):
    assert len(lib) == len(lib.masks) == 5 * 12 and lib.source == "builtin"
    assert set(lib.names) == {"tree", "car", "pedestrian", "pole", "sign"} == set(KINDS)
    assert lib.names == [k for k in KINDS for _ in range(12)]  # fixed order, kind by kind
    assert len(OccluderLibrary.builtin(variants_per_kind=2)) == 10
    assert OccluderLibrary.load().names == OccluderLibrary.builtin().names


def test_builtin_masks_are_binary_tight_and_sized(lib):
    for m, name in zip(lib.masks, lib.names):
        assert m.dtype == np.uint8 and m.ndim == 2, name
        assert set(np.unique(m)) == {0, 1}, name
        # tight crop: the foreground touches all four edges
        assert m[0].any() and m[-1].any() and m[:, 0].any() and m[:, -1].any(), name
        assert 20 <= max(m.shape) <= 420, (name, m.shape)


def test_builtin_realism_proportions(lib):
    aspect = {k: [m.shape[0] / m.shape[1] for m in _by_kind(lib, k)] for k in KINDS}
    assert np.mean(np.array(aspect["pole"]) > 3) >= 0.75  # poles are tall and thin
    assert all(a < 1 for a in aspect["car"])  # cars are wider than tall
    assert np.mean(np.array(aspect["pedestrian"]) > 1) >= 0.8
    assert np.mean(np.array(aspect["sign"]) > 1.2) >= 0.75
    # the post of a pole or sign is thin: the lower half is narrow compared with the height
    for kind in ("pole", "sign"):
        thin = [m[m.shape[0] // 2:].sum(axis=1).mean() < 0.12 * m.shape[0] for m in _by_kind(lib, kind)]
        assert np.mean(thin) >= 0.75, kind
    # cars are solid bodies
    assert min(m.mean() for m in _by_kind(lib, "car")) > 0.55


def test_builtin_ground_contact_details(lib):
    # cars stand on two separate wheels/tyres, not on a flat slab
    assert all(_runs(m[-1]) >= 2 for m in _by_kind(lib, "car"))
    # most trees: crown much wider than the trunk at the ground
    trees = _by_kind(lib, "tree")
    trunked = [m for m in trees if m[: m.shape[0] // 2].sum(axis=1).max() > 2.5 * m[-1].sum()]
    assert len(trunked) >= len(trees) // 2
    # signs/poles stand on a narrow foot
    for m in _by_kind(lib, "sign") + _by_kind(lib, "pole"):
        assert m[-1].sum() < 0.7 * m.shape[1] or m.shape[1] < 25


# ---------------------------------------------------------------- from_dir

def _write_cutouts(folder):
    rng = np.random.default_rng(0)
    rgba = np.zeros((40, 50, 4), np.uint8)
    rgba[..., :3] = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)  # colour noise must not matter
    rgba[10:30, 5:20, 3] = 255
    assert cv2.imwrite(str(folder / "a_rect.png"), rgba)
    gray = np.zeros((60, 60), np.uint8)
    cv2.circle(gray, (30, 30), 12, 255, -1)
    assert cv2.imwrite(str(folder / "b_disc.PNG"), gray)
    rgb = np.zeros((30, 30, 3), np.uint8)
    rgb[5:25, 8:12] = (255, 255, 255)
    rgb[5:9, 8:20] = (200, 220, 240)
    rgb[20:30, 20:30] = (60, 60, 60)  # dark: background
    assert cv2.imwrite(str(folder / "c_rgb.png"), rgb)
    disc = np.zeros((25, 25), np.uint8)
    cv2.circle(disc, (12, 12), 12, 1, -1)
    ell = np.zeros((20, 12), np.uint8)
    ell[:, :4] = 1
    ell[:4, :] = 1
    return {"a_rect": np.ones((20, 15), np.uint8), "b_disc": disc, "c_rgb": ell}


def test_from_dir_loads_known_shapes(tmp_path):
    expected = _write_cutouts(tmp_path)
    (tmp_path / "notes.txt").write_text("not a png")
    (tmp_path / "sub").mkdir()
    lib = OccluderLibrary.from_dir(tmp_path)
    assert lib.names == ["a_rect", "b_disc", "c_rgb"] and lib.source == str(tmp_path)
    for m, name in zip(lib.masks, lib.names):
        assert m.dtype == np.uint8
        np.testing.assert_array_equal(m, expected[name], err_msg=name)
    assert OccluderLibrary.load(tmp_path).names == lib.names


def test_from_dir_skips_bad_files_with_warning(tmp_path, caplog):
    expected = _write_cutouts(tmp_path)
    (tmp_path / "x.png").write_bytes(b"definitely not an image")
    assert cv2.imwrite(str(tmp_path / "y_empty.png"), np.zeros((8, 8), np.uint8))
    with caplog.at_level(logging.WARNING, logger="cuboidgen.occluders"):
        lib = OccluderLibrary.from_dir(tmp_path)
    assert lib.names == sorted(expected)
    warned = " ".join(r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    assert "x.png" in warned and "y_empty.png" in warned


def test_from_dir_ignores_a_cutout_still_being_written(tmp_path):
    """`cuboidgen occluders` writes each cut-out under a temporary name, then renames it: a
    generator loading the folder meanwhile takes the finished files only."""
    from shared.files import temporary_name

    expected = _write_cutouts(tmp_path)
    (tmp_path / "a_rect.png").rename(tmp_path / temporary_name("a_rect.png"))
    assert OccluderLibrary.from_dir(tmp_path).names == sorted(set(expected) - {"a_rect"})


def test_from_dir_errors_name_the_folder(tmp_path):
    with pytest.raises(ValueError, match="no PNG files") as e:
        OccluderLibrary.from_dir(tmp_path)
    assert str(tmp_path) in str(e.value)
    missing = tmp_path / "nope"
    with pytest.raises(ValueError, match="no such folder") as e:
        OccluderLibrary.from_dir(missing)
    assert str(missing) in str(e.value)
    (tmp_path / "x.png").write_bytes(b"junk")
    with pytest.raises(ValueError, match="none of its 1 PNG") as e:
        OccluderLibrary.from_dir(tmp_path)
    assert str(tmp_path) in str(e.value)


# ---------------------------------------------------------------- extract_cityscapes

H, W = 64, 128


def _disc(r):
    d = np.zeros((2 * r + 1, 2 * r + 1), np.uint8)
    cv2.circle(d, (r, r), r, 1, -1)
    return d


def _frame(root, split, city, seq, frame, pieces, with_instances=True):
    """pieces: (labelId, instanceId, top, left, 0/1 shape)."""
    label = np.zeros((H, W), np.uint8)
    label[:12] = 11  # building at the top; never an occluder
    inst = label.astype(np.uint16)
    for lid, iid, top, left, shape in pieces:
        sl = (slice(top, top + shape.shape[0]), slice(left, left + shape.shape[1]))
        label[sl][shape > 0], inst[sl][shape > 0] = lid, iid
    d = root / "gtFine" / split / city
    d.mkdir(parents=True, exist_ok=True)
    stem = f"{city}_{seq}_{frame}"
    assert cv2.imwrite(str(d / f"{stem}_gtFine_labelIds.png"), label)
    if with_instances:
        assert cv2.imwrite(str(d / f"{stem}_gtFine_instanceIds.png"), inst)


@pytest.fixture
def cityscapes(tmp_path):
    root = tmp_path / "cs"
    person = np.zeros((44, 12), np.uint8)
    person[5:] = 1
    person[:5, 3:9] = 1  # head
    car_a, car_b = np.ones((20, 30), np.uint8), np.ones((22, 30), np.uint8)
    blob = np.ones((20, 25), np.uint8)
    expected = {
        "car_aachen_000000_000019_0.png": car_a, "car_aachen_000000_000019_1.png": car_b,
        "person_aachen_000000_000019_0.png": person,
        "vegetation_bonn_000001_000042_0.png": blob, "vegetation_bonn_000001_000042_1.png": _disc(14),
        "car_bonn_000001_000042_0.png": np.ones((20, 25), np.uint8),
        "car_bonn_000002_000007_0.png": np.ones((20, 50), np.uint8),
    }
    _frame(root, "train", "aachen", "000000", "000019", [
        (26, 26000, 30, 10, car_a), (26, 26001, 30, 40, car_b),  # touching cars: instances keep them apart
        (24, 24000, 15, 85, person),
        (17, 17, 0, 100, np.ones((50, 10), np.uint8)),  # pole cut by the top border
        (20, 20, 40, 112, np.ones((5, 5), np.uint8)),  # traffic sign below min_pixels
    ])
    _frame(root, "train", "bonn", "000001", "000042", [
        (21, 21, 14, 10, blob), (21, 21, 31, 56, _disc(14)),  # vegetation: stuff, two components
        (26, 26, 16, 95, np.ones((20, 25), np.uint8)),  # crowd car region: no instance id
    ])
    _frame(root, "val", "bonn", "000002", "000007", [  # no instanceIds: components for all
        (26, 26000, 30, 20, np.ones((20, 25), np.uint8)), (26, 26001, 30, 45, np.ones((20, 25), np.uint8)),
    ], with_instances=False)
    return root, expected


def test_extract_cityscapes_counts_names_and_shapes(cityscapes, tmp_path):
    root, expected = cityscapes
    out = tmp_path / "out" / "nested"
    counts = extract_cityscapes(root, out)
    assert counts == {"car": 4, "person": 1, "vegetation": 2}
    assert sorted(p.name for p in out.iterdir()) == sorted(expected)
    for name, shape in expected.items():
        img = cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED)
        assert img.ndim == 2 and img.dtype == np.uint8 and set(np.unique(img)) <= {0, 255}, name
        np.testing.assert_array_equal(img // 255, shape, err_msg=name)
    lib = OccluderLibrary.from_dir(out)  # the output is directly usable as a library
    assert lib.names == sorted(n[:-4] for n in expected)


def test_extract_cityscapes_restrictions(cityscapes, tmp_path):
    root, expected = cityscapes
    assert extract_cityscapes(root, tmp_path / "cars", classes=["car"]) == {"car": 4}
    assert sorted(p.name for p in (tmp_path / "cars").iterdir()) == sorted(n for n in expected if n.startswith("car_"))
    assert extract_cityscapes(root, tmp_path / "val", splits=("val", "nosuch")) == {"car": 1}
    # a lower threshold lets the small traffic sign through; the border-cut pole stays out
    small = extract_cityscapes(root, tmp_path / "small", min_pixels=10)
    assert small["traffic sign"] == 1 and "pole" not in small
    assert "traffic light" in DEFAULT_CLASSES and DEFAULT_CLASSES["car"] == 26


def test_extract_cityscapes_errors(cityscapes, tmp_path):
    root, _ = cityscapes
    with pytest.raises(ValueError, match="no gtFine folder") as e:
        extract_cityscapes(tmp_path / "nowhere", tmp_path / "o")
    assert str(tmp_path / "nowhere") in str(e.value)
    with pytest.raises(ValueError, match="'lorry'.*car"):
        extract_cityscapes(root, tmp_path / "o", classes=["car", "lorry"])
    (tmp_path / "empty" / "gtFine" / "train").mkdir(parents=True)
    with pytest.raises(ValueError, match="no labelIds files"):
        extract_cityscapes(tmp_path / "empty", tmp_path / "o")
