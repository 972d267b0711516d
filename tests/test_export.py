"""ONNX export: `cuboidtrain export` writes a checked file whose onnxruntime outputs match torch eager.

Models are 64 px with random weights, saved as checkpoints so that the CLI path
(checkpoint -> load_model -> export) is the one exercised. Each export takes a few
seconds, so the files are made once per module.
"""
import json

import numpy as np
import onnx
import pytest
import torch
from typer.testing import CliRunner

from cuboidtrain.models.checkpoint import load_model, save_checkpoint
from cuboidtrain.cli import app
from cuboidtrain.infer.export import FORMAT, OUTPUTS, OnnxPipeline, read_metadata
from cuboidtrain.models.refine import refine
from shared.sample import signed
from shared.shapes import get_shape
from tests.conftest import build_sample, tiny_model, train_config

SIZE = 64
STEP = 7  # the checkpoints' step, which the metadata must carry
runner = CliRunner()


# --- builders ------------------------------------------------------------------

def cli_export(checkpoint, out, *extra) -> None:
    result = runner.invoke(app, ["export", "--checkpoint", str(checkpoint), "--onnx", str(out), *extra])
    assert result.exit_code == 0, result.output


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """{(shape, K): (checkpoint path, onnx path)} for box K=1, box K=2 and twobox K=1."""
    folder = tmp_path_factory.mktemp("export")
    files = {}
    for shape, seed in (("box", 1), ("twobox", 2)):
        model = tiny_model(shape, SIZE, seed=seed)
        ckpt = save_checkpoint(folder / f"{shape}.pt", model, train_config(shape=shape, size=SIZE), step=STEP)
        for steps in ((1, 2) if shape == "box" else (1,)):
            out = folder / f"{shape}-k{steps}.onnx"
            cli_export(ckpt, out, "--refine-steps", str(steps))
            files[shape, steps] = ckpt, out
    return files


def masks(shape: str, kind: str, batch: int) -> np.ndarray:
    """(B, 1, S, S) float32 +-1: random pixels, or the noisy masks of generated samples."""
    if kind == "random":
        bits = np.random.default_rng(batch).random((batch, 1, SIZE, SIZE)) < 0.4
    else:
        bits = np.stack([build_sample(seed, shape, size=SIZE).noisy for seed in range(batch)])[:, None]
    return signed(bits)


def eager(model, mask: np.ndarray, steps: int) -> dict[str, np.ndarray]:
    """infer's own chain in torch (CuboidNet.forward): K Refiner passes, then S on R's output, then T."""
    with torch.inference_mode():
        out = model(torch.from_numpy(mask), steps)
        alone, _, _ = refine(model.refiner, torch.from_numpy(mask), steps)
    assert out.refine_steps == steps and torch.equal(out.refined, alone)
    return {"refined": out.refined.numpy(), "heatmaps": out.heatmaps.numpy(), "keypoints": out.keypoints.numpy(),
            "ratios": out.ratios.numpy()}


def assert_close(onnx_out: dict, torch_out: dict) -> None:
    assert set(onnx_out) == set(OUTPUTS)
    for name, atol in (("refined", 1e-4), ("heatmaps", 1e-4), ("keypoints", 1e-3), ("ratios", 1e-4)):
        assert onnx_out[name].shape == torch_out[name].shape, name
        np.testing.assert_allclose(onnx_out[name], torch_out[name], rtol=0, atol=atol, err_msg=name)


def one_line_error(result, message: str) -> None:
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and message in lines[0], result.output


# --- the file ------------------------------------------------------------------

@pytest.mark.parametrize("shape, steps", [("box", 1), ("box", 2), ("twobox", 1)])
def test_export_is_a_valid_onnx_model_with_its_metadata(exported, shape, steps):
    _, path = exported[shape, steps]
    onnx.checker.check_model(str(path))
    proto = onnx.load(str(path), load_external_data=False)
    assert [i.name for i in proto.graph.input] == ["mask"]
    assert [o.name for o in proto.graph.output] == list(OUTPUTS)
    assert proto.graph.input[0].type.tensor_type.shape.dim[0].dim_param == "batch"  # dynamic batch
    geometry = get_shape(shape)
    meta = read_metadata(path)
    assert meta["format"] == FORMAT and meta["version"] == "1"
    assert meta["shape"] == shape and int(meta["size"]) == SIZE and int(meta["refine_steps"]) == steps
    assert float(meta["sigma"]) == train_config(shape=shape, size=SIZE).heatmap_sigma
    assert json.loads(meta["keypoint_names"]) == list(geometry.keypoint_names)
    assert json.loads(meta["ratio_names"]) == list(geometry.ratio_names)
    assert int(meta["checkpoint_step"]) == STEP and meta["input"] == "binary"
    session = OnnxPipeline(path, threads=1, shape=shape, size=SIZE)
    assert session.metadata == meta and (session.shape, session.size, session.refine_steps) == (shape, SIZE, steps)


# --- parity with torch eager ---------------------------------------------------

@pytest.mark.parametrize("shape", ["box", "twobox"])
@pytest.mark.parametrize("kind", ["random", "generated"])
def test_onnxruntime_matches_torch_eager(exported, shape, kind):
    ckpt, path = exported[shape, 1]
    model, _ = load_model(ckpt)
    mask = masks(shape, kind, 3)
    assert_close(OnnxPipeline(path, threads=1).run(mask), eager(model, mask, 1))


def test_dynamic_batch_rows_equal_single_runs(exported):
    _, path = exported["twobox", 1]
    session, mask = OnnxPipeline(path, threads=1), masks("twobox", "generated", 3)
    batched = session.run(mask)
    assert batched["keypoints"].shape == (3, 14, 2) and batched["heatmaps"].shape == (3, 14, SIZE, SIZE)
    for row in range(3):
        single = session.run(mask[row : row + 1])
        assert single["keypoints"].shape == (1, 14, 2) and single["ratios"].shape == (1, 4)
        for name in OUTPUTS:
            np.testing.assert_allclose(single[name][0], batched[name][row], rtol=0, atol=1e-5, err_msg=name)


def test_two_refine_steps_match_infer_refine(exported):
    ckpt, path = exported["box", 2]
    model, _ = load_model(ckpt)
    mask = masks("box", "generated", 2)
    two = OnnxPipeline(path, threads=1).run(mask)
    assert_close(two, eager(model, mask, 2))
    # The second pass is really in the graph: one pass gives a mask farther from it than
    # parity's tolerance (1e-4), and the graph holds the Refiner's convolutions twice.
    one = OnnxPipeline(exported["box", 1][1], threads=1).run(mask)
    assert np.abs(two["refined"] - one["refined"]).max() > 1e-3
    refiner_convs = sum(isinstance(m, torch.nn.Conv2d) for m in model.refiner.modules())
    assert conv_count(path) - conv_count(exported["box", 1][1]) == refiner_convs


def conv_count(path) -> int:
    return sum(node.op_type == "Conv" for node in onnx.load(str(path), load_external_data=False).graph.node)


# --- errors --------------------------------------------------------------------

@pytest.mark.parametrize("args, message", [
    (["--checkpoint", "/nonexistent/last.pt"], "/nonexistent/last.pt: no such file"),
    (["--refine-steps", "-1"], "--refine-steps -1: expected a whole number of passes from 0 to 16"),
    (["--opset", "9"], "--opset 9: expected 11 to 20"),
])
def test_cli_bad_values_are_one_line_errors(exported, tmp_path, args, message):
    ckpt, _ = exported["box", 1]
    base = {"--checkpoint": str(ckpt), "--onnx": str(tmp_path / "out.onnx")}
    base.update(dict(zip(args[::2], args[1::2])))
    one_line_error(runner.invoke(app, ["export", *[x for kv in base.items() for x in kv]]), message)
    assert not (tmp_path / "out.onnx").exists()


def test_cli_rejects_a_file_that_is_not_a_checkpoint(tmp_path, exported):
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    result = runner.invoke(app, ["export", "--checkpoint", str(tmp_path / "bad.pt"), "--onnx", str(tmp_path / "o.onnx")])
    one_line_error(result, "bad.pt: cannot read it: not a cuboid-fit checkpoint")
    assert "Unpickling" not in result.output  # what it is not, not what pickle tripped on
    ckpt, _ = exported["box", 1]  # a torch file cut short: damaged, and the check of its archive says so
    (tmp_path / "cut.pt").write_bytes(ckpt.read_bytes()[:4096])
    result = runner.invoke(app, ["export", "--checkpoint", str(tmp_path / "cut.pt"), "--onnx", str(tmp_path / "o.onnx")])
    one_line_error(result, "cut.pt: damaged: the archive does not read (")
    assert "not a cuboid-fit checkpoint" not in result.output


def foreign_onnx(path) -> None:
    """A valid ONNX model that is not ours: an Identity with no metadata."""
    value = onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])
    out = onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])
    graph = onnx.helper.make_graph([onnx.helper.make_node("Identity", ["x"], ["y"])], "g", [value], [out])
    # IR 8 / opset 17: onnx 1.23 writes IR 14 by default, which onnxruntime 1.30 refuses to load
    model = onnx.helper.make_model(graph, ir_version=8, opset_imports=[onnx.helper.make_opsetid("", 17)])
    onnx.save(model, str(path))


def test_runner_rejects_foreign_files_in_one_line(tmp_path, exported):
    (tmp_path / "model.onnx").write_bytes(b"\x00garbage, not protobuf" * 10)
    foreign_onnx(tmp_path / "identity.onnx")
    _, ours = exported["box", 1]
    cases = [
        (lambda: OnnxPipeline(tmp_path / "model.onnx"), "onnxruntime cannot load it"),
        (lambda: OnnxPipeline(tmp_path / "missing.onnx"), "missing.onnx: no such file"),
        (lambda: OnnxPipeline(tmp_path / "identity.onnx"), f"not a cuboid-fit export (format None, expected {FORMAT!r})"),
        (lambda: read_metadata(tmp_path / "model.onnx"), "cannot read it"),
        (lambda: OnnxPipeline(ours, shape="twobox"), "a 'box' model, expected 'twobox'"),
        (lambda: OnnxPipeline(ours, size=256), "a 64 px model, expected 256 px"),
        (lambda: OnnxPipeline(ours, threads=1).run(np.zeros((1, 1, 32, 32))), "mask (1, 1, 32, 32): expected (B, 1, 64, 64)"),
    ]
    for call, message in cases:
        with pytest.raises(ValueError) as info:
            call()
        assert message in str(info.value) and "\n" not in str(info.value)
