"""infer --cuboid (cuboidtrain.fit.cuboid): the record's keypoints are a box's projection, its
`cuboid` object is whole and finite, and on clean masks the fit is closer to the truth than the
networks' corners; without the option the record is as before."""
from dataclasses import replace

import cv2
import numpy as np
import pytest

from cuboidgen.config import PAPER_CLEAN
from cuboidtrain.fit import cuboid as stage
from cuboidtrain.fit.fitter import Fitter, FitFailure
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.infer.records import to_record, to_records
from shared.files import json_text
from shared.shapes import get_shape
from tests.conftest import build_sample

# (shape, seed) at 128 px, clean scene: small, and a mix of views.
MASKS = [("box", 1), ("box", 2), ("box", 3), ("twobox", 1), ("twobox", 2), ("twobox", 3)]
SIZE = 128


@pytest.fixture(scope="module")
def masks(tmp_path_factory):
    """Clean generated masks written as PNGs, with their samples."""
    folder = tmp_path_factory.mktemp("cuboid")
    samples, paths = [], []
    for shape, seed in MASKS:
        sample = build_sample(seed, shape, size=SIZE, scene=PAPER_CLEAN)
        path = folder / f"{shape}-{seed}.png"
        assert cv2.imwrite(str(path), sample.clean.astype(np.uint8) * 255)
        samples.append(sample)
        paths.append(str(path))
    return paths, samples


@pytest.fixture(scope="module")
def records(masks):
    """Each mask fitted as its own shape class, networks only and with --cuboid."""
    paths, samples = masks
    out = {}
    for cuboid in (False, True):
        fitters = {s: Fitter.from_shipped(FitOptions(shape=s, device="cpu", cuboid=cuboid)) for s in ("box", "twobox")}
        out[cuboid] = [to_record(fitters[s.shape].outcomes([p])[0], cuboid=cuboid) for p, s in zip(paths, samples)]
    return out


def concurrency(shape: str, keypoints) -> float:
    """The largest, over every part and edge direction, of how far its four image edges are from
    meeting in one point (a vanishing point, at infinity for parallel edges): the smallest singular
    value of their four unit line vectors, 0 for a box's projection."""
    points = np.asarray(keypoints, dtype=np.float64)
    worst = 0.0
    for part in get_shape(shape).parts:
        corners = np.hstack([points[list(part)], np.ones((8, 1))])  # box order: bits left 2, bottom 1, front 4
        for bit in (1, 2, 4):
            lines = np.array([np.cross(corners[c], corners[c | bit]) for c in range(8) if not c & bit])
            lines /= np.linalg.norm(lines, axis=1, keepdims=True)
            worst = max(worst, np.linalg.svd(lines, compute_uv=False)[-1])
    return worst


def test_the_keypoints_are_a_box_s_projection(records):
    for fitted, networks in zip(records[True], records[False]):
        assert fitted["error"] is None, fitted["error"]
        assert concurrency(fitted["shape"], fitted["keypoints"]) < 1e-9
    # and the test can tell: the networks' free corners are no box's projection
    assert all(concurrency(r["shape"], r["keypoints"]) > 1e-6 for r in records[False])


def test_the_cuboid_object_is_whole_and_finite(records):
    for record in records[True]:
        json_text(record)  # strict JSON: no NaN or Infinity anywhere
        cuboid = record["cuboid"]
        assert set(cuboid) == {"yaw_deg", "yaw_sd_deg", "pitch_deg", "roll_deg", "focal_px", "focal_sd_px",
                               "principal_px", "intrinsics", "mirror", "iou", "outline_rms_px", "interior", "corners"}
        assert cuboid["interior"] in ("from outline", "from heat maps")
        assert record["shape"] == "box" or cuboid["interior"] == "from heat maps"  # a twobox's outline is no hexagon
        assert cuboid["intrinsics"] == {"focal_px": "fitted", "principal_px": "fitted"}  # nothing was given
        assert cuboid["yaw_sd_deg"] > 0 and (cuboid["focal_sd_px"] is None) == (cuboid["focal_px"] is None)
        assert set(record["ratios_sd"]) == set(record["ratios"]) and list(record)[5] == "ratios_sd"
        assert all(-180 <= cuboid[k] <= 180 for k in ("yaw_deg", "pitch_deg", "roll_deg"))
        assert cuboid["focal_px"] is None or cuboid["focal_px"] > 0
        assert (cuboid["focal_px"] is None) == (cuboid["principal_px"] is None)
        assert 0.9 < cuboid["iou"] <= 1  # a clean mask is explained
        assert record["candidates"][record["shape"]] == cuboid["iou"]
        assert len(cuboid["corners"]) == len(record["keypoints"])
        assert all(isinstance(c["on_outline"], bool) and 0 <= c["score"] <= 1 for c in cuboid["corners"])
        assert any(c["on_outline"] for c in cuboid["corners"])
        assert (get_shape(record["shape"]).ratio_vector(record["ratios"]) > 0).all()  # the box's own, nested form


def test_the_fit_is_closer_to_the_true_corners_than_the_networks_on_clean_masks(masks, records):
    _, samples = masks

    def mean_error(recs):
        return np.mean([np.linalg.norm(np.asarray(r["keypoints"]) - s.keypoints, axis=1).mean()
                        for r, s in zip(recs, samples)])

    assert mean_error(records[True]) <= mean_error(records[False])


def test_without_the_option_the_record_has_no_cuboid(records):
    assert not any("cuboid" in r for r in records[False])


def test_auto_chooses_by_the_fitted_cuboids(masks):
    paths, samples = masks
    fitted = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True)).outcomes(paths[:1] + paths[3:4])
    for record in to_records(fitted, FitOptions(cuboid=True)):
        assert set(record["candidates"]) == {"box", "twobox"}
        assert record["cuboid"]["iou"] == record["candidates"][record["shape"]]
        assert concurrency(record["shape"], record["keypoints"]) < 1e-9


def test_a_non_finite_cuboid_fit_is_an_error_record(masks, monkeypatch):
    real = stage.finished  # every LM fit of the stage, first start or restarted, ends there
    monkeypatch.setattr(stage, "finished", lambda *a, **k: [replace(f, yaw_deg=float("nan")) for f in real(*a, **k)])
    paths, _ = masks
    [failure] = Fitter.from_shipped(FitOptions(shape="box", device="cpu", cuboid=True)).outcomes(paths[:1])
    assert isinstance(failure, FitFailure) and failure.input == paths[0]
    record = to_record(failure, cuboid=True)
    assert record["keypoints"] is None and record["cuboid"] is None
    assert "cuboid fit's yaw/pitch/roll is not finite" in record["error"]


def test_the_panel_of_a_cuboid_fit_draws_its_residual_and_the_networks_corners(tmp_path):
    """With --cuboid the explanation has a tile of the networks' corners against the fitted box and
    one of where box and input disagree, both ways (a legend entry, with a pixel count, for each)."""
    from cuboidtrain.infer.explain import explanation_figure
    import matplotlib.pyplot as plt

    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True, shape="box"))
    mask = cv2.imread("examples/building.png", cv2.IMREAD_UNCHANGED)
    fit = fitter.fit(mask)
    figure = explanation_figure(fit)
    titles = {ax.get_title().split("\n")[0]: ax for ax in figure.axes}
    corners = [t.get_text() for t in titles["networks' corners -> the fitted cuboid"].get_legend().get_texts()]
    residual = [t.get_text() for t in titles[f"silhouette residual, IoU {fit.cuboid.fit.iou:.3f}"].get_legend().get_texts()]
    plt.close(figure)
    assert "networks' corner -> fitted" in corners and "hidden corner (not on the outline)" in corners
    assert [label.split(":")[0] for label in residual[:3]] == ["input, not the box", "box, not the input", "both"]
    model_minus_input = int(residual[1].split(": ")[1].removesuffix(" px"))
    assert model_minus_input > 1000  # the building's occluded holes, inside the box


def fitted_cuboid(shape: str, iou: float, left_height: float = 0.6, split: float = 0.5) -> stage.FittedCuboid:
    """A fitted cuboid of `shape` with the given IoU; a twobox's LEFT part `left_height` times the RIGHT's,
    its RIGHT part `split` of its width."""
    from cuboidtrain.geometry.camera_params import CameraParams, describe

    vector = np.array([0.0, 0.0, 0.1, 0.2, 0.0, 0.0, 0.0, np.log(100.0), 0.2, 64.0, 64.0]
                      + ([split, np.log(left_height)] if shape == "twobox" else []))
    fit = describe(CameraParams(get_shape(shape), vector, False), 0.0, iou=iou)
    return stage.FittedCuboid(fit, np.ones(get_shape(shape).num_keypoints))


@pytest.mark.parametrize("left_height, seam", [(0.6, False), (1 / 0.6, False), (0.85, False), (0.95, True),
                                               (1.0, True), (1 / 0.95, True)])
def test_a_twobox_of_nearly_equal_heights_is_a_box_with_a_seam(left_height, seam):
    reason = stage.implausible(fitted_cuboid("twobox", 0.9, left_height).fit)
    assert (reason is not None) == seam
    if seam:
        assert "a box with a seam" in reason
    assert stage.implausible(fitted_cuboid("box", 0.9).fit) is None


@pytest.mark.parametrize("split, sliver", [(0.5, False), (0.3, False), (0.7, False), (0.22, False), (0.18, True),
                                           (0.85, True), (0.05, True)])
@pytest.mark.parametrize("left_height", [0.6, 1 / 0.6])
def test_a_twobox_with_a_part_narrower_than_a_fifth_of_it_is_a_box_with_a_sliver(split, sliver, left_height):
    """The generator draws each part at 30% of the width or more: a narrower one is a neighbour's corner or a
    chimney beside a box, whichever part is the taller."""
    fit = fitted_cuboid("twobox", 0.9, left_height, split).fit
    share = min(split, 1 - split)
    widths = [fit.ratios[part]["width_height"] * height for part, height in (("right", 1.0), ("left", left_height))]
    assert min(widths) / sum(widths) == pytest.approx(share)  # the fit's own parts, as the rule reads them
    reason = stage.implausible(fit)
    assert (reason is not None) == sliver
    if sliver:
        assert f"its narrower part is {100 * share:.0f}% of its width" in reason and "a box with a sliver" in reason


@pytest.mark.parametrize("box_iou, twobox_iou, left_height, chosen, warned", [
    (0.90, 0.903, 0.6, "box", False),  # within the margin: the simpler class
    (0.90, 0.91, 0.6, "twobox", False),  # clearly better and plausible
    (0.90, 0.95, 0.97, "box", True),  # clearly better, but a box with a seam: set aside, and said
    (0.90, 0.80, 0.97, "box", False),  # worse anyway: nothing to say
])
def test_the_fitted_cuboids_choose_the_class_plausibly(box_iou, twobox_iou, left_height, chosen, warned):
    from tests.test_infer import candidate

    cuboids = {"box": fitted_cuboid("box", box_iou), "twobox": fitted_cuboid("twobox", twobox_iou, left_height)}
    for order in (["box", "twobox"], ["twobox", "box"]):
        best, warnings = stage.choose_cuboid([candidate(s, 0.5) for s in order], cuboids)
        assert best.shape == chosen and best.confidence == cuboids[chosen].fit.iou
        assert bool(warnings) == warned
        if warned:
            assert "twobox cuboid explained the input better" in warnings[0] and "box with a seam" in warnings[0]


def runaway_twobox(iou: float, split: float = 1.1, k: float = 0.2) -> stage.FittedCuboid:
    """A twobox fit gone wrong: its split outside its width (the LEFT part's width negative) or,
    with a large `k`, its camera inside it."""
    from cuboidtrain.geometry.camera_params import CameraParams, describe

    vector = np.array([0.0, 0.0, 0.1, 0.2, 0.0, 0.0, 0.0, np.log(100.0), k, 64.0, 64.0, split, np.log(0.6)])
    return stage.FittedCuboid(describe(CameraParams(get_shape("twobox"), vector, False), 0.0, iou=iou),
                              np.ones(get_shape("twobox").num_keypoints))


def test_a_part_of_no_width_or_a_camera_inside_is_no_building():
    assert stage.impossible(fitted_cuboid("twobox", 0.9).fit) is None
    assert stage.impossible(fitted_cuboid("box", 0.9).fit) is None
    assert "a part of no width or depth" in stage.impossible(runaway_twobox(0.9, split=1.1).fit)
    assert "the camera is inside or behind it" in stage.impossible(runaway_twobox(0.9, split=0.5, k=3.0).fit)


def test_a_twobox_that_is_no_building_is_set_aside_and_a_forced_one_is_said_so():
    from tests.test_infer import candidate

    cuboids = {"box": fitted_cuboid("box", 0.80), "twobox": runaway_twobox(0.95)}
    best, warnings = stage.choose_cuboid([candidate("box", 0.5), candidate("twobox", 0.5)], cuboids)
    assert best.shape == "box" and len(warnings) == 1 and "a part of no width or depth" in warnings[0]
    best, warnings = stage.choose_cuboid([candidate("twobox", 0.5)], {"twobox": cuboids["twobox"]})
    assert best.shape == "twobox" and warnings == [
        f"the twobox cuboid is no building: {stage.impossible(cuboids['twobox'].fit)}; its 3D answer is not to be trusted"]


def test_when_no_class_is_plausible_all_are_judged_alike():
    from tests.test_infer import candidate

    cuboids = {"twobox": fitted_cuboid("twobox", 0.9, 1.0)}
    best, warnings = stage.choose_cuboid([candidate("twobox", 0.5)], cuboids)
    assert best.shape == "twobox" and warnings == []


def test_a_batch_of_fits_gives_each_mask_s_own_fit(masks):
    """eval fits a batch of masks at once (`Fitter.fit_cuboids`): each mask's rows read its own outline
    (padded to the longest), field, corners and anchor, so every fit equals the mask fitted alone;
    a small mask's shorter outline pads the batch."""
    from cuboidtrain.geometry.outline import MaskTarget

    paths, samples = masks
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))
    small = cv2.resize(samples[0].clean.astype(np.uint8), (40, 40), interpolation=cv2.INTER_NEAREST) > 0
    inputs = [s.clean for s in samples] + [small]
    candidates, targets = [], []
    for mask in inputs:
        for model in fitter.models:
            candidates.append(fitter.fit_framed(model, *fitter.framed(model, mask)))
            targets.append(MaskTarget.of(mask))
    assert len({len(t.outline) for t in targets}) > 1  # the outlines differ in length: padding is tested
    together = fitter.fit_cuboids(candidates, targets)
    for candidate, target, fitted in zip(candidates, targets, together):
        [alone] = fitter.fit_cuboids([candidate], [target])
        assert fitted.fit.shape == candidate.shape
        np.testing.assert_allclose(fitted.fit.keypoints, alone.fit.keypoints, atol=1e-6)
        assert fitted.fit.iou == pytest.approx(alone.fit.iou, abs=1e-9)
        np.testing.assert_allclose(fitted.corner_scores, alone.corner_scores, atol=1e-9)


def test_the_soft_optimizer_fits_a_real_cuboid_through_the_command(masks, tmp_path):
    """`infer --optimizer soft`: the soft-rasterised fit answers in the same record, a box's
    projection, and differs from LM's; it is the cuboid fit's, so not with --networks-only."""
    from typer.testing import CliRunner

    from cuboidtrain.cli import app

    paths, _ = masks
    records = {}
    for optimizer in ("lm", "soft"):
        out = tmp_path / f"{optimizer}.json"
        result = CliRunner().invoke(app, ["infer", paths[0], "--shape", "box", "--optimizer", optimizer, "--device", "cpu",
                                          "--json", str(out)])
        assert result.exit_code == 0, result.output
        [records[optimizer]] = __import__("json").loads(out.read_text())
    soft = records["soft"]
    assert soft["cuboid"]["iou"] > 0.9 and concurrency("box", soft["keypoints"]) < 1e-9
    assert soft["keypoints"] != records["lm"]["keypoints"]
    result = CliRunner().invoke(app, ["infer", paths[0], "--optimizer", "soft", "--networks-only"])
    assert result.exit_code == 2 and "--optimizer soft with --networks-only" in result.output
    assert len(result.output.strip().splitlines()) == 1
