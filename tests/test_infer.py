"""Inference: the records of docs/contract.md ("The infer record"), keypoints in input pixels, iterative refinement, confidence, the CLI.

Models are 32 px with random weights; where a test needs known outputs, the
Refiner or Tabulator of a real CuboidNet is swapped for a stub.
"""
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn
from typer.testing import CliRunner

from cuboidtrain.models.checkpoint import save_checkpoint
from cuboidtrain.cli import app
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.fit.candidates import RICHER_SHAPE_MARGIN, Candidate, choose
from cuboidtrain.geometry.silhouette import confidence, model_silhouette
from cuboidtrain.models.refine import refine
from cuboidtrain.fit.masks import components, frame, load_mask
from shared.sample import signed
from shared.shapes import get_shape
from tests.conftest import build_sample, infer_paths, tiny_model, train_config, with_generated_pdm

SIZE = 32
RECORD_KEYS = {"input", "shape", "confidence", "keypoints", "ratios", "refine_steps", "refine_converged", "error",
               "warnings", "candidates"}
runner = CliRunner()


# --- builders ------------------------------------------------------------------

class Identity(nn.Module):
    """A stationary Refiner: its output is its input."""

    def forward(self, mask):
        return mask


class Erode(nn.Module):
    """A Refiner that peels one pixel off the object per pass, at half strength so that
    passing its raw output back (instead of the binarised one) would show."""

    def __init__(self):
        super().__init__()
        self.inputs = []

    def forward(self, mask):
        self.inputs.append(mask.clone())
        padded = F.pad(mask, (1, 1, 1, 1), value=-1.0)  # outside the image is background
        return 0.5 * -F.max_pool2d(-padded, 3, stride=1)  # a 3x3 min-pool


class Recording(Identity):
    """A stationary Refiner that keeps the last mask it was shown (the framed component)."""

    def forward(self, mask):
        self.last = (mask[0, 0] > 0).numpy()
        return mask


class FixedTabulator(nn.Module):
    """A Tabulator that returns known model-px keypoints (from a function of nothing, or of the
    framed mask the test recorded), whatever the heat maps."""

    def __init__(self, points, num_ratios: int):
        super().__init__()
        self.points, self.num_ratios = points, num_ratios

    def forward(self, heatmaps):
        points = self.points() if callable(self.points) else self.points
        keypoints = torch.as_tensor(np.asarray(points, dtype=np.float64))[None]
        return keypoints, torch.ones(1, self.num_ratios)


def stub_model(shape: str, refiner: nn.Module | None = None, points=None):
    model = tiny_model(shape, SIZE)
    if refiner is not None:
        model.refiner = refiner
    if points is not None:
        model.tabulator = FixedTabulator(points, len(get_shape(shape).ratio_names))
    return model.eval()


def write_png(path: Path, mask: np.ndarray) -> str:
    cv2.imwrite(str(path), mask.astype(np.uint8) * 255)
    return str(path)


def rectangles(shape, *boxes) -> np.ndarray:
    """A bool (H, W) mask holding the given (x0, y0, x1, y1) rectangles, ends inclusive."""
    mask = np.zeros(shape, bool)
    for x0, y0, x1, y1 in boxes:
        mask[y0 : y1 + 1, x0 : x1 + 1] = True
    return mask


def hexagon(shape=(60, 90)) -> np.ndarray:
    mask = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(mask, np.array([[12, 20], [40, 6], [70, 15], [72, 45], [45, 55], [10, 42]], np.int32), 1)
    return mask.astype(bool)


def rect_keypoints(framed: np.ndarray, n: int) -> np.ndarray:
    """n keypoints on the corners of a framed rectangle: their silhouette is the rectangle exactly."""
    ys, xs = np.nonzero(framed)
    corners = np.array([[xs.max(), ys.min()], [xs.max(), ys.max()], [xs.min(), ys.min()], [xs.min(), ys.max()]], float)
    return np.resize(corners, (n, 2))  # box: each corner twice; twobox: both parts span the rectangle


@pytest.fixture(scope="module")
def random_models():
    return [tiny_model("box", SIZE, seed=1).eval(), tiny_model("twobox", SIZE, seed=2).eval()]


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory, random_models):
    folder = tmp_path_factory.mktemp("ckpt")
    return {m.shape: save_checkpoint(folder / f"{m.shape}.pt", m, train_config(shape=m.shape, size=SIZE), step=0)
            for m in random_models}


# --- records -------------------------------------------------------------------

def check_record(record: dict, path: str, shape: str | None = None) -> None:
    assert set(record) == RECORD_KEYS
    assert record["input"] == path and record["error"] is None
    assert record["shape"] in ("box", "twobox") and (shape is None or record["shape"] == shape)
    geometry = get_shape(record["shape"])
    assert isinstance(record["confidence"], float) and 0 <= record["confidence"] <= 1
    assert len(record["keypoints"]) == geometry.num_keypoints
    assert all(len(p) == 2 and all(isinstance(v, float) for v in p) for p in record["keypoints"])
    ratios = record["ratios"]
    if record["shape"] == "box":
        assert set(ratios) == {"depth_height", "width_height"}
    else:
        assert set(ratios) == {"right", "left"} and all(set(r) == {"depth_height", "width_height"} for r in ratios.values())
    assert isinstance(record["refine_steps"], int) and record["refine_steps"] >= 1
    assert record["candidates"][record["shape"]] == record["confidence"]


@pytest.mark.parametrize("shape", ["auto", "box", "twobox"])
def test_records_follow_the_design_schema(tmp_path, random_models, shape):
    path = write_png(tmp_path / "house.png", hexagon())
    records = infer_paths([path], random_models, shape=shape)
    assert len(records) == 1
    check_record(records[0], path, None if shape == "auto" else shape)
    assert set(records[0]["candidates"]) == ({"box", "twobox"} if shape == "auto" else {shape})
    assert json.loads(json.dumps(records)) == records


def test_keypoints_are_mapped_back_to_input_pixels(tmp_path):
    points = np.random.default_rng(0).uniform(-0.5, SIZE - 0.5, (8, 2))
    path = write_png(tmp_path / "house.png", hexagon((75, 110)))
    [record] = infer_paths([path], [stub_model("box", points=points)], margin=0.15)
    _, framing = frame(components(load_mask(Path(path)))[0], SIZE, margin=0.15)
    assert framing.scale != 1 and np.allclose(record["keypoints"], framing.to_input(points), atol=1e-9)


def test_fit_with_one_step_is_the_chained_forward(random_models):
    model, framed = random_models[0], rectangles((SIZE, SIZE), (6, 9, 25, 22))
    result = Fitter([model], FitOptions(device="cpu")).fit_framed(model, framed)
    with torch.inference_mode():
        expected = model(torch.from_numpy(signed(framed))[None, None])
    assert np.allclose(result.keypoints, expected.keypoints[0].numpy(), atol=1e-6)
    assert result.refined.shape == (SIZE, SIZE) and result.heatmaps.shape == (8, SIZE, SIZE)
    assert result.refine_steps == 1 and set(result.ratios) == {"depth_height", "width_height"}


# --- iterative refinement (Figure 7) -------------------------------------------

def test_a_stationary_refiner_stops_after_two_passes(tmp_path):
    model = stub_model("box", refiner=Identity())
    mask = torch.from_numpy(signed(rectangles((SIZE, SIZE), (4, 4, 20, 20))))[None, None]
    refined, steps, converged = refine(model.refiner, mask, None)
    assert steps == 2 and converged and torch.equal(refined, mask)  # the second pass changed nothing
    assert refine(model.refiner, mask, 5)[1] == 5
    path = write_png(tmp_path / "a.png", hexagon())
    assert infer_paths([path], [model], refine_steps=None)[0]["refine_steps"] == 2


def test_an_eroding_refiner_runs_to_the_limit_on_binary_inputs(tmp_path):
    model = stub_model("box", refiner=(erode := Erode()))
    full = torch.ones(1, 1, SIZE, SIZE)  # 16 one-pixel peels to empty: every pass changes something
    refined, steps, converged = refine(model.refiner, full, 20)
    assert steps == 20 and converged and not (refined > 0).any()  # a fixed K is what was asked for
    assert all(set(x.unique().tolist()) <= {-1.0, 1.0} for x in erode.inputs)  # the sign went back in, not 0.5
    refined, steps, converged = refine(model.refiner, full, 5)
    assert steps == 5 and int((refined > 0).sum()) == (SIZE - 10) ** 2
    path = write_png(tmp_path / "a.png", hexagon())
    assert infer_paths([path], [model], refine_steps=3)[0]["refine_steps"] == 3


def test_the_first_pass_reads_a_grey_input_as_given_and_later_passes_its_sign():
    erode = Erode()
    grey = torch.full((1, 1, SIZE, SIZE), -1.0)
    grey[..., 4:20, 4:20], grey[..., 4:20, 20] = 1.0, 0.2  # a column 60% covered
    for steps in (3, None):
        erode.inputs.clear()
        refine(erode, grey, steps)
        assert torch.equal(erode.inputs[0], grey)  # not binarised: the grey edge reaches R
        assert all(set(x.unique().tolist()) <= {-1.0, 1.0} for x in erode.inputs[1:])


def test_auto_refinement_that_never_settles_keeps_the_first_pass_and_says_so(tmp_path):
    # A drifting Refiner (here one that peels a pixel every pass) must not eat the mask under
    # auto: the record says it did not converge, and the mask is R's first pass.
    model = stub_model("box", refiner=Erode())
    full = torch.ones(1, 1, SIZE, SIZE)
    refined, steps, converged = refine(model.refiner, full, None, max_steps=5)
    assert not converged and steps == 1 and int((refined > 0).sum()) == (SIZE - 2) ** 2
    path = write_png(tmp_path / "a.png", hexagon())
    record = infer_paths([path], [model], refine_steps=None)[0]
    assert record["refine_converged"] is False and record["refine_steps"] == 1
    assert any("did not settle" in w for w in record["warnings"])
    assert infer_paths([path], [model], refine_steps=1)[0]["refine_converged"] is True


class FirstStillRestEroding(nn.Module):
    """A Refiner that leaves the batch's first mask as it is and erodes the others."""

    def forward(self, mask):
        return torch.cat([mask[:1], Erode()(mask[1:])])


def test_auto_refinement_decides_per_mask_in_a_batch():
    # eval refines batches: one mask that never settles must not hold back (or throw away)
    # the passes of one that did
    full = torch.ones(2, 1, SIZE, SIZE)
    refined, steps, converged = refine(FirstStillRestEroding(), full, None, max_steps=5)
    assert steps == 2 and not converged
    assert torch.equal(refined[0], full[0])  # settled after its second pass
    assert int((refined[1] > 0).sum()) == (SIZE - 2) ** 2  # never settled: its first pass


# --- confidence ----------------------------------------------------------------

def test_confidence_is_high_for_the_true_keypoints_and_lower_when_perturbed():
    sample = build_sample(seed=3, shape="box", size=48)
    true = confidence("box", sample.keypoints, signed(sample.clean))
    assert true > 0.97
    assert model_silhouette("box", sample.keypoints, 48).sum() > 0
    rng = np.random.default_rng(0)
    for scale in (1.5, 4.0):
        perturbed = sample.keypoints + rng.normal(0, scale, sample.keypoints.shape)
        assert confidence("box", perturbed, signed(sample.clean)) < true


def fitted_record(tmp_path, mask: np.ndarray, points) -> dict:
    """infer's record for `mask` with a box model whose T returns `points` (model px, or a function
    of the framed mask)."""
    path = write_png(tmp_path / "m.png", mask)
    framed, _ = frame(components(load_mask(Path(path)))[0], SIZE)
    [record] = infer_paths([path], [stub_model("box", Identity(), points(framed) if callable(points) else points)])
    return record


def test_keypoints_outside_the_input_are_warned_about_and_lower_the_confidence(tmp_path):
    block = rectangles((60, 80), (20, 15, 60, 45))
    inside = fitted_record(tmp_path, block, lambda framed: rect_keypoints(framed, 8))
    assert not any("outside the input" in w for w in inside["warnings"])

    def two_far_below(framed):  # the bottom corners pushed down past the 60 px image's edge
        points = rect_keypoints(framed, 8)
        points[[1, 3]] += (0, 3 * SIZE)
        return points

    outside = fitted_record(tmp_path, block, two_far_below)
    assert any(w.startswith("2 of 8 keypoints lie outside the input image") for w in outside["warnings"])
    assert all(not (0 <= y <= 59) for _, y in np.asarray(outside["keypoints"])[[1, 3]])
    assert outside["confidence"] < 0.75 * inside["confidence"]


def test_the_stages_hand_on_typed_results_and_none_edits_another(tmp_path):
    # The chosen Candidate keeps its own IoU; the Fit's lowered confidence and warnings are the
    # Scores made from it (chain.score), and an explanation reads that same Candidate.
    path = write_png(tmp_path / "m.png", rectangles((60, 80), (20, 15, 60, 45)))
    framed, _ = frame(components(load_mask(Path(path)))[0], SIZE)
    points = rect_keypoints(framed, 8)
    points[[1, 3]] += (0, 3 * SIZE)  # two corners far below the image: guessed
    fit = Fitter([stub_model("box", Identity(), points)], FitOptions(device="cpu")).fit(path)
    candidate = fit.explanation.candidate
    assert isinstance(candidate, Candidate) and candidate.shape == fit.shape == "box"
    assert candidate.confidence == fit.candidates["box"] > fit.confidence  # lowered in the Fit, not in place
    assert np.allclose(candidate.framing.to_input(candidate.keypoints), fit.keypoints)
    assert np.array_equal(candidate.framed, framed) and fit.explanation.mask.shape == (60, 80)
    assert any("outside the input image" in w for w in fit.warnings)


def test_a_mask_that_fills_the_frame_is_not_confident(tmp_path):
    block = rectangles((60, 80), (20, 15, 60, 45))
    whole = fitted_record(tmp_path, block, lambda framed: rect_keypoints(framed, 8))
    # All but a notch in the top edge (an all-foreground mask has no outline at all: it is refused,
    # tests/test_not_a_mask.py): its outline is almost all the image's edge.
    full = np.ones((60, 80), bool)
    full[0, 40:42] = False
    full = fitted_record(tmp_path, full, lambda framed: rect_keypoints(framed, 8))
    assert whole["confidence"] > 0.9
    assert full["confidence"] < 0.05  # a perfect box fit to an outline that is the image's edge explains nothing
    assert any("outline lies on the image's edge" in w for w in full["warnings"])
    cut = fitted_record(tmp_path, rectangles((60, 80), (20, 15, 60, 59)), lambda framed: rect_keypoints(framed, 8))
    assert full["confidence"] < cut["confidence"] < whole["confidence"]  # cut along one side: in between


@pytest.mark.parametrize("winner", ["box", "twobox"])
def test_auto_picks_the_model_with_the_higher_confidence(tmp_path, winner):
    path = write_png(tmp_path / "block.png", rectangles((50, 70), (10, 8, 55, 40)))
    framed, _ = frame(components(load_mask(Path(path)))[0], SIZE)
    bad = np.resize([[1.0, 1.0], [4.0, 1.0], [1.0, 4.0]], (14, 2))  # a small triangle in a corner
    models = [stub_model(s, Identity(), rect_keypoints(framed, n) if s == winner else bad[:n])
              for s, n in (("box", 8), ("twobox", 14))]
    [record] = infer_paths([path], models)
    assert record["shape"] == winner and record["confidence"] > 0.9  # shrinking rounds the corners a little
    loser = "twobox" if winner == "box" else "box"
    assert record["candidates"][loser] < 0.1


def test_a_picture_that_cannot_be_made_is_a_warning_and_the_records_survive(tmp_path, random_models):
    good = write_png(tmp_path / "good.png", hexagon())

    def broken(index, path, fit):
        raise OSError(28, "No space left on device")

    [record] = infer_paths([good], random_models, explain=broken)
    assert record["error"] is None and record["keypoints"] is not None
    assert "no explanation: [Errno 28] No space left on device" in record["warnings"]


@pytest.mark.parametrize("box, twobox, chosen", [
    (0.90, 0.91, "box"), (0.90, 0.90 + RICHER_SHAPE_MARGIN, "box"), (0.90, 0.93, "twobox"), (0.95, 0.50, "box"),
])
def test_the_twobox_must_explain_clearly_more_than_the_box(box, twobox, chosen):
    fits = [candidate("twobox", twobox), candidate("box", box)]
    assert choose(fits).shape == chosen  # in any order of the models given
    assert choose(fits[::-1]).shape == chosen


def candidate(shape: str, confidence: float) -> Candidate:
    n, empty = get_shape(shape).num_keypoints, np.zeros((SIZE, SIZE))
    return Candidate(shape=shape, keypoints=np.zeros((n, 2)), ratios={}, confidence=confidence, refine_steps=1,
                     refine_converged=True, refined=empty, heatmaps=np.zeros((n, SIZE, SIZE)), framed=empty > 0)


def test_a_requested_shape_without_its_model_is_an_error(random_models):
    with pytest.raises(ValueError, match="no twobox model"):
        infer_paths(["x.png"], random_models[:1], shape="twobox")
    with pytest.raises(ValueError, match="same shape"):
        infer_paths(["x.png"], [random_models[0], random_models[0]])


# --- inputs that fail, components ----------------------------------------------

def test_bad_inputs_give_error_records_and_the_others_still_run(tmp_path, random_models):
    good = write_png(tmp_path / "good.png", hexagon())
    empty = write_png(tmp_path / "empty.png", np.zeros((40, 40), bool))
    (tmp_path / "notes.png").write_text("not an image")
    paths = [str(tmp_path / "missing.png"), empty, good, str(tmp_path / "notes.png")]
    records = infer_paths(paths, random_models)
    assert [r["input"] for r in records] == paths
    for record, words in zip(records, ["cannot read", "empty mask", None, "cannot read"]):
        assert set(record) == RECORD_KEYS
        if words is None:
            check_record(record, good)
        else:
            assert record["keypoints"] is None and words in record["error"] and "\n" not in record["error"]


def test_all_components_gives_one_record_per_component(tmp_path):
    big, small = (5, 5, 40, 30), (60, 35, 80, 52)
    path = write_png(tmp_path / "two.png", rectangles((60, 90), big, small))
    refiner = Recording()
    model = stub_model("box", refiner, lambda: rect_keypoints(refiner.last, 8))  # the framed component's corners
    records = infer_paths([path], [model], all_components=True)
    assert [r["component"] for r in records] == [0, 1] and [r["input"] for r in records] == [path, path]
    for record, (x0, y0, x1, y1) in zip(records, (big, small)):
        assert set(record) == RECORD_KEYS | {"component"}
        xs, ys = np.array(record["keypoints"]).T
        assert np.allclose([xs.min(), ys.min(), xs.max(), ys.max()], [x0, y0, x1, y1], atol=0.75)
    assert len(infer_paths([path], [model])) == 1 and "component" not in infer_paths([path], [model])[0]


def test_a_building_cut_in_pieces_by_an_occluder_is_fitted_whole(tmp_path):
    """A pole cuts the building in two: the fit frames both pieces (masks.silhouette), not the
    larger one alone; --all-components still fits each piece on its own."""
    left, right = (5, 5, 40, 30), (43, 5, 80, 30)  # a 2 px pole at x = 41, 42
    path = write_png(tmp_path / "cut.png", rectangles((60, 90), left, right))
    refiner = Recording()
    model = stub_model("box", refiner, lambda: rect_keypoints(refiner.last, 8))  # the framed object's corners
    [record] = infer_paths([path], [model])
    xs, ys = np.array(record["keypoints"]).T
    model_px = 76 / (SIZE * (1 - 2 * 0.1))  # one model pixel in input pixels: the framing's resolution
    assert np.allclose([xs.min(), ys.min(), xs.max(), ys.max()], [5, 5, 80, 30], atol=model_px)  # not 5 .. 40
    assert len(infer_paths([path], [model], all_components=True)) == 2


def test_a_grey_input_model_is_shown_the_mask_as_each_pixel_s_covered_share(tmp_path):
    path = write_png(tmp_path / "rect.png", rectangles((60, 90), (10, 10, 70, 50)))
    class Shown(Recording):  # and the mask itself, as R read it
        def forward(self, mask):
            self.raw = mask[0, 0].clone().numpy()
            return super().forward(mask)

    shown = {}
    for grey in (False, True):
        refiner = Shown()
        model = stub_model("box", refiner, lambda: rect_keypoints(refiner.last, 8))
        model.grey_input = grey
        infer_paths([path], [model])
        shown[grey] = refiner.raw
    framed, _ = frame(load_mask(Path(path)), SIZE, grey=True)
    np.testing.assert_allclose(shown[True], framed * 2 - 1, atol=1e-6)
    assert set(np.unique(shown[False])) == {-1.0, 1.0} and np.array_equal(shown[False] > 0, shown[True] >= 0)
    assert ((shown[True] > -1) & (shown[True] < 1)).sum() > 20  # the rectangle's edges, between the levels
    candidate = Fitter([model], FitOptions(device="cpu")).fit_framed(model, framed)  # the explanation's x1 tile
    np.testing.assert_array_equal(candidate.framed, framed)


# --- the command line ----------------------------------------------------------

def test_cli_writes_json_to_a_file_and_to_stdout(tmp_path, checkpoints):
    good, missing = write_png(tmp_path / "good.png", hexagon()), str(tmp_path / "missing.png")
    out = tmp_path / "out.json"
    args = ["infer", good, missing, "--checkpoint", str(checkpoints["box"]), "--checkpoint", str(checkpoints["twobox"]),
            "--networks-only"]
    result = runner.invoke(app, args + ["--json", str(out), "--refine-steps", "auto"])
    assert result.exit_code == 1, result.output  # one input failed: the others are written, the status says so
    assert "1 of 2 inputs have an error" in result.output
    records = json.loads(out.read_text())
    check_record(records[0], good)
    assert records[1]["error"] and records[1]["keypoints"] is None
    assert not list(tmp_path.glob(".tmp-*"))
    result = runner.invoke(app, args[:2] + args[3:] + ["--json", "-", "--shape", "twobox"])
    assert result.exit_code == 0, result.output
    records = json.loads(result.stdout)
    check_record(records[0], good, "twobox")
    assert records[0]["refine_steps"] == 1


@pytest.mark.parametrize("extra, message", [
    (["--checkpoint", "{twobox}", "--checkpoint", "{twobox}"], "second 'twobox' model"),
    (["--checkpoint", "{tmp}/nope.pt"], "no such file"),
    (["--checkpoint", "{twobox}", "--shape", "box"], "no box model"),
    (["--checkpoint", "{box}", "--refine-steps", "many"], "--refine-steps 'many'"),
    (["--checkpoint", "{box}", "--margin", "0.7"], "--margin 0.7"),
    (["--checkpoint", "{box}", "--extractor", "pdm", "--pdm-components", "1.5"], "--pdm-components '1.5'"),
    (["--checkpoint", "{box}", "--overlay", "{tmp}/p.jpg"], "--overlay needs --explain DIR"),
    (["--checkpoint", "{box}", "--explain", "{tmp}/x", "--overlay", "{tmp}/p.jpg", "--overlay", "{tmp}/p.jpg"],
     "--overlay given 2 times for 1 inputs"),
])
def test_cli_bad_options_are_one_line_errors(tmp_path, checkpoints, extra, message):
    good = write_png(tmp_path / "good.png", hexagon())
    names = {"twobox": checkpoints["twobox"], "box": checkpoints["box"], "tmp": tmp_path}
    result = runner.invoke(app, ["infer", good] + [a.format(**names) for a in extra])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], result.output


# --- more bad inputs, warnings, extractors ----------------------------------------

def huge_png(path: Path, width: int, height: int) -> str:
    """A PNG whose header claims width x height (its pixel data is a tiny image's: never decoded)."""
    ok, data = cv2.imencode(".png", np.zeros((4, 4), np.uint8))
    data = bytearray(data.tobytes())
    data[16:24] = width.to_bytes(4, "big") + height.to_bytes(4, "big")
    path.write_bytes(bytes(data))
    return str(path)


def test_a_huge_image_is_refused_before_decoding_and_the_others_still_run(tmp_path, random_models):
    huge = huge_png(tmp_path / "huge.png", 40_000, 30_000)
    good = write_png(tmp_path / "good.png", hexagon())
    full = write_png(tmp_path / "full.png", np.ones((40, 50), bool))
    records = infer_paths([huge, good, full], random_models)
    assert "40000 x 30000 px is too large" in records[0]["error"] and records[0]["keypoints"] is None
    check_record(records[1], good)
    # An all-foreground mask has no background, so no outline: an error record, saying what reads it otherwise.
    assert records[2]["keypoints"] is None and "every pixel is the object" in records[2]["error"]
    assert "pass --invert" in records[2]["error"]


def test_a_silhouette_cut_by_the_border_gets_a_warning_naming_the_sides(tmp_path, random_models):
    cut = write_png(tmp_path / "cut.png", rectangles((60, 90), (0, 20, 30, 59)))
    inside = write_png(tmp_path / "inside.png", hexagon())
    records = infer_paths([cut, inside], random_models)
    border = [[w for w in r["warnings"] if "border" in w] for r in records]  # random T may add others
    assert len(border[0]) == 1 and "bottom and left border" in border[0][0]
    assert "truncated" in border[0][0] and records[0]["keypoints"] is not None
    assert border[1] == []


@pytest.mark.parametrize("extractor", ["argmax", "centre-of-mass", "dark", "pdm"])
def test_an_extractor_replaces_t_s_keypoints_but_not_its_ratios(tmp_path, extractor):
    path = write_png(tmp_path / "rect.png", rectangles((60, 90), (10, 10, 70, 50)))
    refiner = Recording()
    tabulated = lambda: rect_keypoints(refiner.last, 8)  # noqa: E731
    model = with_generated_pdm(stub_model("box", refiner, tabulated))
    model.estimator = TrueHeatmaps(lambda: rect_keypoints(refiner.last, 8) + 0.6)  # S's peaks 0.6 px off T's
    by_t = infer_paths([path], [model])[0]
    decoded = infer_paths([path], [model], extractor=extractor)[0]
    assert decoded["ratios"] == by_t["ratios"]
    shift = np.array(decoded["keypoints"]) - np.array(by_t["keypoints"])
    framing = frame(load_mask(Path(path)), SIZE)[1]
    if extractor in ("dark", "centre-of-mass"):  # sub-pixel: the 0.6 model px shift, in input px
        assert np.allclose(shift, 0.6 / framing.scale, atol=0.15 / framing.scale)
    elif extractor == "argmax":  # whole pixels: the peak's pixel, one model px off T's corners
        assert np.allclose(shift, 1 / framing.scale, atol=1e-9)
    else:  # the PDM moves the points: a rectangle's doubled corners are no cuboid
        assert np.abs(shift).max() > 0.1 / framing.scale


class TrueHeatmaps(nn.Module):
    """An Estimator that draws Gaussians at given model-px points (a function of nothing)."""

    def __init__(self, points):
        super().__init__()
        self.points = points

    def forward(self, mask):
        from cuboidtrain.models.codec import render_heatmaps

        return render_heatmaps(torch.as_tensor(self.points(), dtype=torch.float32)[None], mask.shape[-1], 1.0)
