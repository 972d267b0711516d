"""Irregular buildings (cuboidgen/irregular.py): the deviations leave the truth the box's, change the
silhouette only where each belongs, stay inside the picture, and the scene is reproducible from a seed."""
from dataclasses import replace

import cv2
import numpy as np
import pytest

from cuboidgen.config import IRREGULAR, SCENES
from cuboidgen.irregular import (PartFrame, degrade, draw_deviations, irregular, structure_points,
                                 with_structures)
from cuboidgen.scene import draw_view
from cuboidgen.synth import make_sample
from shared.camera import Cuboid, Intrinsics
from shared.raster import rasterize
from shared.sample import encode
from shared.shapes import get_shape
from tests.test_checks import library

SEEDS = range(24)


def view_and_deviations(shape_name: str, seed: int, **forced):
    """A view of the irregular scene framed with its deviations, drawn as the generator draws it; `forced`
    sets probabilities (1 or 0) to draw one kind alone."""
    scene = replace(IRREGULAR, **forced)
    shape = get_shape(shape_name)
    rng = np.random.default_rng(seed)
    deviations = draw_deviations(shape, scene, rng)
    view = draw_view(shape, scene, 256, rng, beside=lambda camera: structure_points(deviations, shape, camera))
    return shape, view, deviations


ALONE = {kind: {f"{other}_probability": float(other == kind)
                for other in ("roof", "chimney", "parapet", "neighbour", "blob", "low_res")}
         for kind in ("roof", "chimney", "parapet", "neighbour", "blob", "low_res")}


def test_only_the_irregular_preset_draws_deviations():
    assert [name for name, scene in SCENES.items() if irregular(scene)] == ["irregular"]


@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_the_truth_is_the_box_whatever_the_deviations(shape):
    """The keypoints are the drawn cuboid's projection (its params give them back), the ratios its own and
    the clean mask its own silhouette, while the noisy mask shows the deviations."""
    geometry, differs = get_shape(shape), 0
    for seed in SEEDS:
        sample = make_sample(shape, IRREGULAR, 256, seed, library())
        params = sample.params
        keypoints = Cuboid.from_params(params).keypoints(geometry, Intrinsics.from_params(params))
        assert np.allclose(sample.keypoints, keypoints)
        assert (sample.clean == rasterize(geometry, sample.keypoints, 256)).all()
        assert {d["kind"] for d in params["deviations"]} <= {"roof", "chimney", "parapet", "neighbour", "blob", "low_res"}
        differs += bool((sample.noisy & ~sample.clean).any())
    assert differs >= len(SEEDS) // 2  # most irregular buildings show something the box does not


@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_framing_the_deviations_moves_the_box_only_by_the_frames_scale_and_shift(shape):
    """The same draws framed with and without the deviations: the same 3D box and ratios, and keypoints
    that differ by one scale and one shift (the framing), never by the box's shape."""
    geometry = get_shape(shape)
    for seed in SEEDS:
        rng = np.random.default_rng(seed)
        deviations = draw_deviations(geometry, IRREGULAR, rng)
        state = rng.bit_generator.state
        plain = draw_view(geometry, IRREGULAR, 256, rng)
        rng.bit_generator.state = state
        framed = draw_view(geometry, IRREGULAR, 256, rng,
                           beside=lambda camera: structure_points(deviations, geometry, camera))
        assert np.allclose(plain.points3d, framed.points3d) and plain.ratios == framed.ratios
        a, b = plain.keypoints - plain.keypoints.mean(0), framed.keypoints - framed.keypoints.mean(0)
        scale = np.linalg.norm(b) / np.linalg.norm(a)
        assert np.allclose(a * scale, b, atol=1e-6)


@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_a_part_frame_spans_its_part(shape):
    geometry = get_shape(shape)
    _, view, _ = view_and_deviations(shape, 3)
    for part in geometry.parts:
        frame = PartFrame(view.points3d, part)
        corners = frame.block((0.0, 1.0), (-1.0, 0.0), (0.0, 1.0))
        assert sorted(map(tuple, np.round(corners, 9))) == sorted(map(tuple, np.round(view.points3d[list(part)], 9)))


@pytest.mark.parametrize("kind", ["roof", "chimney", "parapet"])
@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_a_roof_chimney_or_parapet_only_adds_above_its_parts_top(kind, shape):
    """Pixels are only added, and only above the lowest of the part's top corners: nothing reaches down the walls."""
    geometry = get_shape(shape)
    added_any = 0
    for seed in SEEDS:
        _, view, deviations = view_and_deviations(shape, seed, **ALONE[kind])
        clean = rasterize(geometry, view.keypoints, 256)
        built = with_structures(clean, deviations, geometry, view)
        assert (built >= clean).all()
        added = np.argwhere(built & ~clean)
        added_any += len(added) > 0
        if len(added):
            top = geometry.having("TOP")
            part = [i for i in geometry.parts[deviations[0]["part"]] if i in top]
            assert added[:, 0].max() <= view.keypoints[part, 1].max() + 1
    assert added_any >= len(SEEDS) // 3  # a parapet on a back edge hides behind the front one, seen from below


@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_a_neighbour_joins_the_building_on_its_side(shape):
    """A neighbour's corner adds pixels on its side of the building, merged in: one silhouette, not two."""
    geometry = get_shape(shape)
    for seed in SEEDS:
        _, view, deviations = view_and_deviations(shape, seed, **ALONE["neighbour"])
        clean = rasterize(geometry, view.keypoints, 256)
        built = with_structures(clean, deviations, geometry, view)
        added = np.argwhere(built & ~clean)
        if not len(added):
            continue
        centre = np.argwhere(clean)[:, 1].mean()
        assert (added[:, 1].mean() < centre) == (deviations[0]["side"] == "left")
        assert cv2.connectedComponents(built.view(np.uint8))[0] == 2  # the background and one building


@pytest.mark.parametrize(("kind", "reach"), [("blob", lambda d: d["radius"] + 4 * d["wobble"] + 2),
                                             ("low_res", lambda d: d["factor"] + 1)])
def test_blobby_edges_and_low_resolution_change_only_pixels_near_the_outline(kind, reach):
    for seed in SEEDS:
        shape, view, deviations = view_and_deviations("twobox", seed, **ALONE[kind])
        mask = rasterize(shape, view.keypoints, 256)
        degraded = degrade(mask, deviations, np.random.default_rng(seed))
        changed = degraded != mask
        assert changed.any()
        inside = cv2.distanceTransform(mask.view(np.uint8), cv2.DIST_L2, 5)
        outside = cv2.distanceTransform((~mask).view(np.uint8), cv2.DIST_L2, 5)
        assert np.maximum(inside, outside)[changed].max() <= reach(deviations[0])


@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_the_picture_holds_every_deviation(shape):
    """The framing holds the roof and the neighbour: no noisy mask is cut by the image's edge."""
    for seed in SEEDS:
        noisy = make_sample(shape, IRREGULAR, 128, seed, library()).noisy
        assert not (noisy[0].any() or noisy[-1].any() or noisy[:, 0].any() or noisy[:, -1].any())


@pytest.mark.parametrize("shape", ["box", "twobox", "mix"])
def test_the_scene_is_the_same_for_a_seed_and_differs_between_seeds(shape):
    first = [encode(make_sample(shape, IRREGULAR, 64, seed, library())) for seed in (5, 6)]
    assert first == [encode(make_sample(shape, IRREGULAR, 64, seed, library())) for seed in (5, 6)]
    assert first[0] != first[1]
