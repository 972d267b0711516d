"""R, S, T and CuboidNet for every registered arch (timm's pattern: shapes, ranges, no NaNs,
every parameter learns, ONNX parity), seeded construction, TrainConfig.validate, and checkpoint
round trips."""
from __future__ import annotations

import functools
import os
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch import nn

from cuboidtrain.models.checkpoint import FORMAT, VERSION, load_checkpoint, load_model, save_checkpoint
from cuboidtrain.data.sampler import loader_state
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.data.sampler import LoaderState
from cuboidtrain.infer.export import OnnxPipeline, export_model
from cuboidtrain.models.codec import render_heatmaps
from cuboidtrain.models.networks import ARCHS, ChainOutput, Estimator, Refiner, Tabulator, build_model, check_arch
from shared.shapes import get_shape

SHAPES = ["box", "twobox"]
ARCH_NAMES = list(ARCHS)
SIZE = 32  # px: the smallest size a ResNet-18 U-Net takes
B = 4  # batch: at 32 px the stride-32 features are 1x1, and BatchNorm needs more than 2 values


@functools.cache
def tiny_model(shape: str, arch: str = "paper"):
    """One model per (shape, arch) for the whole file; tests that change it only touch grads or BN stats."""
    return build_model(shape, SIZE, seed=0, arch=arch)


def counts(shape: str) -> tuple[int, int]:
    geometry = get_shape(shape)
    return geometry.num_keypoints, len(geometry.ratio_names)


def masks(batch: int = B, size: int = SIZE, seed: int = 0) -> torch.Tensor:
    """(B, 1, size, size) +1/-1 masks: a random rectangle each, like a crude silhouette."""
    g = torch.Generator().manual_seed(seed)
    out = -torch.ones(batch, 1, size, size)
    for b in range(batch):
        x0, y0 = torch.randint(0, size // 2, (2,), generator=g).tolist()
        x1, y1 = torch.randint(size // 2 + 1, size, (2,), generator=g).tolist()
        out[b, 0, y0:y1, x0:x1] = 1.0
    return out


def heatmaps(n: int, batch: int = B, size: int = SIZE, seed: int = 0) -> torch.Tensor:
    return torch.rand(batch, n, size, size, generator=torch.Generator().manual_seed(seed))


# ---- the registry ---------------------------------------------------------------------


def test_the_registry_holds_the_papers_arch_and_a_compact_one():
    assert {"paper", "compact", "tiny"} <= set(ARCHS)
    paper, compact = build_model("box", 64, arch="paper"), build_model("box", 64, arch="compact")
    size = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert size(compact) * 10 < size(paper)  # compact is an order of magnitude smaller
    assert isinstance(paper.refiner, Refiner) and isinstance(paper.tabulator, Tabulator)


def test_an_unknown_arch_is_a_value_error_naming_the_choices():
    with pytest.raises(ValueError, match=r"arch 'resnet50': expected one of paper, compact, slim, tiny"):
        check_arch("resnet50")
    with pytest.raises(ValueError, match="arch 'resnet50'"):
        TrainConfig(arch="resnet50").validate()


# ---- shapes, ranges, NaNs -------------------------------------------------------------


@pytest.mark.parametrize("arch", ARCH_NAMES)
@pytest.mark.parametrize("shape", SHAPES)
def test_cuboidnet_forward_shapes_and_ranges(shape, arch):
    n, r = counts(shape)
    model = tiny_model(shape, arch).eval()
    with torch.no_grad():
        out = model(masks(2))
    assert isinstance(out, ChainOutput) and (out.refine_steps, out.refine_converged) == (1, True)
    assert out.refined.shape == (2, 1, SIZE, SIZE)
    assert out.heatmaps.shape == (2, n, SIZE, SIZE)
    assert out.keypoints.shape == (2, n, 2) and out.tabulated is out.keypoints  # no extractor here: T's
    assert out.ratios.shape == (2, r)
    for name in ("refined", "heatmaps", "keypoints", "ratios"):
        value = getattr(out, name)
        assert value.dtype == torch.float32, name
        assert torch.isfinite(value).all(), name
    assert out.refined.min() >= -1 and out.refined.max() <= 1
    assert out.heatmaps.min() >= 0 and out.heatmaps.max() <= 1
    low, high = model.tabulator.keypoint_range()
    assert out.keypoints.min() >= low and out.keypoints.max() <= high
    assert (out.ratios > 0).all()


@pytest.mark.parametrize("arch", ARCH_NAMES)
@pytest.mark.parametrize("shape", SHAPES)
def test_each_network_alone_has_its_documented_shape(shape, arch):
    n, r = counts(shape)
    model = tiny_model(shape, arch).eval()
    x = masks(2)
    with torch.no_grad():
        refined = model.refiner(x)
        maps = model.estimator(x)
        keypoints, ratios = model.tabulator(heatmaps(n, 2))
    assert refined.shape == (2, 1, SIZE, SIZE) and refined.abs().max() <= 1
    assert maps.shape == (2, n, SIZE, SIZE) and 0 <= maps.min() and maps.max() <= 1
    assert keypoints.shape == (2, n, 2) and ratios.shape == (2, r)
    assert torch.isfinite(keypoints).all() and (ratios > 0).all()


@pytest.mark.parametrize("arch", ARCH_NAMES)
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("scale", [1e3, -1e3])
def test_keypoints_stay_in_range_even_for_extreme_heatmaps(shape, arch, scale):
    # Saturating inputs must not push a coordinate past what the readout can express, nor to NaN.
    n, _ = counts(shape)
    tabulator = tiny_model(shape, arch).tabulator.eval()
    with torch.no_grad():
        keypoints, _ = tabulator(heatmaps(n, 2) * scale)
    low, high = tabulator.keypoint_range()
    assert torch.isfinite(keypoints).all()
    assert keypoints.min() >= low and keypoints.max() <= high
    assert low <= -0.5 and high >= SIZE - 0.5  # every arch can reach the image's edges


@pytest.mark.parametrize("arch", ["compact", "tiny"])
@pytest.mark.parametrize("size", [32, 64])
def test_the_spatial_expectation_tabulator_reads_true_maps_to_a_hundredth_of_a_pixel(arch, size):
    # Untrained, T's logits are gain * log(map): a true Gaussian map's mean is its centre. Corners
    # up to the grid's border outside the image are Gaussians cut by the edge: read less exactly.
    tabulator = build_model("twobox", size, seed=1, arch=arch).tabulator.eval()
    low, high = tabulator.keypoint_range()
    inside = torch.rand(3, 14, 2, generator=torch.Generator().manual_seed(size)) * (size - 9) + 4
    with torch.no_grad():
        keypoints, _ = tabulator(render_heatmaps(inside, size, 2.0))
    assert (keypoints - inside).abs().max() < 0.01
    assert low < -2 and high > size + 1  # the grid reaches beyond the frame


@pytest.mark.parametrize("arch", ARCH_NAMES)
def test_the_registry_builds_at_other_sizes(arch):
    model = build_model("box", 64, arch=arch).eval()
    with torch.no_grad():
        out = model(masks(2, 64))
    assert out.heatmaps.shape == (2, 8, 64, 64) and out.keypoints.shape == (2, 8, 2)


# ---- every parameter learns -----------------------------------------------------------


@pytest.mark.parametrize("arch", ARCH_NAMES)
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("part", ["refiner", "estimator", "tabulator"])
def test_every_parameter_receives_a_gradient(shape, part, arch):
    n, _ = counts(shape)
    net = getattr(tiny_model(shape, arch), part).train()
    net.zero_grad(set_to_none=True)
    out = net(heatmaps(n) if part == "tabulator" else masks())
    outputs = out if isinstance(out, tuple) else (out,)
    low, high = net.keypoint_range() if part == "tabulator" else {"refiner": (-1, 1), "estimator": (0, 1)}[part]
    assert low <= outputs[0].min() and outputs[0].max() <= high  # train mode keeps the ranges too
    sum(o.sum() for o in outputs).backward()
    params = dict(net.named_parameters())
    assert params
    dead = [name for name, p in params.items() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not dead, f"{part} parameters without gradient: {dead}"
    assert all(torch.isfinite(p.grad).all() for p in params.values())
    net.zero_grad(set_to_none=True)


# ---- ONNX parity ----------------------------------------------------------------------


@pytest.mark.parametrize("arch", ARCH_NAMES)
def test_onnxruntime_matches_torch_for_every_arch(arch, tmp_path):
    model = build_model("twobox", SIZE, seed=4, arch=arch).eval()
    path = export_model(model, tmp_path / f"{arch}.onnx", model.sigma)
    x = masks(3)
    got = OnnxPipeline(path, threads=1).run(x.numpy())
    with torch.no_grad():
        want = model(x)
    for name, atol in (("refined", 1e-4), ("heatmaps", 1e-4), ("keypoints", 1e-3), ("ratios", 1e-4)):
        np.testing.assert_allclose(got[name], getattr(want, name).numpy(), rtol=0, atol=atol, err_msg=f"{arch} {name}")


# ---- construction ---------------------------------------------------------------------


@pytest.mark.parametrize("arch", ARCH_NAMES)
@pytest.mark.parametrize("shape", SHAPES)
def test_build_model_is_seeded_and_leaves_the_global_rng_alone(shape, arch):
    torch.manual_seed(123)
    expected_draw = torch.rand(3)
    torch.manual_seed(123)
    a = build_model(shape, SIZE, seed=5, arch=arch)
    assert torch.equal(torch.rand(3), expected_draw)  # build_model forks the RNG
    b = build_model(shape, SIZE, seed=5, arch=arch)
    c = build_model(shape, SIZE, seed=6, arch=arch)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert list(sa) == list(sb) == list(sc)
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    # every randomly initialised weight (conv, linear) differs with another seed
    random_init = [f"{name}.weight" for name, m in a.named_modules() if isinstance(m, (nn.Conv2d, nn.Linear))]
    assert len(random_init) > 20
    same = [k for k in random_init if torch.equal(sa[k], sc[k])]
    assert not same, same


@pytest.mark.parametrize("size", [32, 64])
def test_fcns_keep_full_resolution_and_tabulator_takes_the_size(size):
    torch.manual_seed(0)
    x = masks(2, size)
    refiner, estimator, tabulator = Refiner().eval(), Estimator(8).eval(), Tabulator(8, 2, size).eval()
    with torch.no_grad():
        refined, maps = refiner(x), estimator(x)
        keypoints, ratios = tabulator(maps)
    assert refined.shape == (2, 1, size, size)
    assert maps.shape == (2, 8, size, size)
    assert keypoints.shape == (2, 8, 2) and ratios.shape == (2, 2)
    assert keypoints.min() >= -0.5 and keypoints.max() <= size - 0.5


# ---- TrainConfig.validate -------------------------------------------------------------


@pytest.mark.parametrize("changes, message", [
    ({"size": 48}, "--size 48"),
    ({"size": 16}, "--size 16"),
    ({"phase": "3"}, "--phase '3'"),
    ({"phase": "finetune"}, "--phase finetune needs --init"),
    ({"phase": "e2e", "init": "p1/last.pt"}, "--phase e2e"),
    ({"shape": "pyramid"}, "'pyramid'"),
    ({"steps": 10, "epochs": 2}, "--steps or --epochs"),
    ({"batch_size": 0}, "--batch-size 0"),
    ({"steps": -3}, "--steps -3"),
    ({"lr_schedule": "step"}, "--lr-schedule 'step'"),
    ({"lr_schedule": "cosine"}, "--lr-schedule cosine needs --steps N or --max-minutes"),
    ({"sigma": -1.0}, "--sigma -1.0"),
    ({"lr": 0.0}, "--lr 0.0"),
    ({"weight_decay": -1e-3}, "--weight-decay -0.001"),
    ({"loader_workers": -1}, "--loader-workers -1"),
    ({"max_minutes": 0}, "--max-minutes 0"),
    ({"device": "tpu"}, "--device 'tpu'"),
    ({"grey_input": True, "reframe": False}, "--grey-input needs --reframe"),
])
def test_validate_rejects_bad_values_naming_them(changes, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        TrainConfig(**changes).validate()


@pytest.mark.parametrize("changes", [
    {"size": 32},
    {"size": 64, "shape": "twobox"},
    {"phase": "finetune", "init": "p2/last.pt"},
    {"phase": "finetune", "resume": True},
    {"phase": "e2e"},
    {"lr_schedule": "cosine", "steps": 100},
    {"device": "cuda:1", "loader_workers": 0, "sigma": 0.5},
])
def test_validate_accepts_good_values(changes):
    config = TrainConfig(**changes)
    assert config.validate() is config


def test_config_dict_round_trip_and_resolved_sigma():
    config = TrainConfig(shape="twobox", size=64, steps=9, lr_schedule="cosine")
    assert TrainConfig.from_dict(config.to_dict()) == config
    assert TrainConfig.from_dict({**config.to_dict(), "from_the_future": 1}) == config
    assert TrainConfig(size=32).resolved().sigma == 1.0
    assert TrainConfig(size=512).resolved().sigma == 4.0
    assert TrainConfig(size=512, sigma=1.5).resolved().sigma == 1.5


# ---- checkpoints ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """shape -> (model, path): each shape's model saved once (the files are ~150 MB)."""
    folder = tmp_path_factory.mktemp("checkpoints")
    out = {}
    for shape in SHAPES:
        model = build_model(shape, SIZE, seed=3).eval()
        config = TrainConfig(shape=shape, size=SIZE, phase="2", steps=50)
        loader = LoaderState(epoch=2, order=["a.cub", "b.cub", "c.cub"], position=1)
        path = save_checkpoint(folder / shape / "last.pt", model, config, step=7, loader=loader,
                               metrics={"D_T": 0.25})
        out[shape] = model, path
    return out


@pytest.mark.parametrize("shape", SHAPES)
def test_checkpoint_round_trip_gives_the_same_weights_and_outputs(saved, shape):
    model, path = saved[shape]
    loaded, ckpt = load_model(path)
    assert not loaded.training
    assert (loaded.shape, loaded.size) == (shape, SIZE)
    a, b = model.state_dict(), loaded.state_dict()
    assert list(a) == list(b)
    assert all(torch.equal(a[k], b[k]) for k in a)
    x = masks(2, seed=4)
    with torch.no_grad():
        want, got = model.eval()(x), loaded(x)
    assert all(torch.equal(getattr(want, k), getattr(got, k)) for k in ("refined", "heatmaps", "keypoints", "ratios"))
    assert ckpt["format"] == FORMAT and ckpt["version"] == VERSION
    assert (ckpt["shape"], ckpt["size"], ckpt["step"], ckpt["sigma"]) == (shape, SIZE, 7, 1.0)
    assert TrainConfig.from_dict(ckpt["config"]) == TrainConfig(shape=shape, size=SIZE, phase="2", steps=50, sigma=1.0)
    assert loader_state(ckpt) == LoaderState(2, ["a.cub", "b.cub", "c.cub"], 1)
    assert ckpt["metrics"] == {"D_T": 0.25} and ckpt["optimizer"] is None


def test_a_checkpoint_keeps_whether_its_model_reads_grey_inputs(saved, tmp_path):
    model, binary_path = saved["box"]
    assert load_model(binary_path)[0].grey_input is False
    config = TrainConfig(shape="box", size=SIZE, phase="2", steps=50, grey_input=True)
    grey_path = save_checkpoint(tmp_path / "grey.pt", model, config, step=7)
    loaded, ckpt = load_model(grey_path)
    assert loaded.grey_input is True and ckpt["config"]["grey_input"] is True
    old = {**torch.load(binary_path, weights_only=False)}
    old["config"] = {k: v for k, v in old["config"].items() if k != "grey_input"}  # written before the option
    torch.save(old, tmp_path / "old.pt")
    assert load_model(tmp_path / "old.pt")[0].grey_input is False


@pytest.mark.parametrize("shape", SHAPES)
def test_saving_leaves_no_temporary_file(saved, shape):
    _, path = saved[shape]
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.pt"]


def test_load_model_with_the_wrong_shape_or_size_names_both(saved):
    _, path = saved["box"]
    with pytest.raises(ValueError, match=r"'box' model, expected 'twobox'"):
        load_model(path, shape="twobox")
    with pytest.raises(ValueError, match=r"32 px model, expected 64 px"):
        load_model(path, shape="box", size=64)
    loaded, _ = load_model(path, shape="box", size=SIZE)  # the right ones pass
    assert loaded.shape == "box"


def test_truncated_foreign_and_missing_files_are_value_errors(saved, tmp_path):
    _, path = saved["box"]
    with open(path, "rb") as f:
        head = f.read(1 << 20)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(head)
    with pytest.raises(ValueError, match=r"truncated\.pt: damaged: the archive does not read .*torn copy"):
        load_model(truncated)
    text = tmp_path / "notes.pt"
    text.write_text("not a checkpoint\n")
    with pytest.raises(ValueError, match=r"notes\.pt: cannot read it"):
        load_model(text)
    foreign = tmp_path / "foreign.pt"
    torch.save({"state_dict": {"w": torch.zeros(2)}}, foreign)
    with pytest.raises(ValueError, match="not a cuboid-fit checkpoint"):
        load_model(foreign)
    with pytest.raises(ValueError, match="no such file"):
        load_model(tmp_path / "missing.pt")


def test_another_checkpoint_version_is_refused_naming_both(tmp_path):
    path = tmp_path / "future.pt"
    torch.save({"format": FORMAT, "version": VERSION + 1, "shape": "box", "size": SIZE}, path)
    with pytest.raises(ValueError, match=rf"version {VERSION + 1}, expected {VERSION}"):
        load_checkpoint(path)


def stub_model(value: float):
    """save_checkpoint only needs shape, size, arch and state_dict: enough to test the file handling."""
    return SimpleNamespace(shape="box", size=SIZE, arch="tiny", state_dict=lambda: {"w": torch.full((3,), value)})


def test_saving_again_replaces_the_file_atomically(tmp_path):
    path = tmp_path / "run" / "last.pt"
    save_checkpoint(path, stub_model(1.0), TrainConfig(size=SIZE), step=1)
    save_checkpoint(path, stub_model(2.0), TrainConfig(size=SIZE), step=2)
    ckpt = load_checkpoint(path)
    assert ckpt["step"] == 2 and torch.equal(ckpt["model"]["w"], torch.full((3,), 2.0))
    assert os.listdir(path.parent) == ["last.pt"]


def test_a_failed_save_keeps_the_old_checkpoint_and_no_temporary_file(tmp_path, monkeypatch):
    path = tmp_path / "last.pt"
    save_checkpoint(path, stub_model(1.0), TrainConfig(size=SIZE), step=1)

    def half_written(obj, f, *args, **kwargs):  # `f`: the file-like save_checkpoint writes through
        f.write(b"PK\x03\x04 half a zip")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", half_written)
    with pytest.raises(OSError):
        save_checkpoint(path, stub_model(2.0), TrainConfig(size=SIZE), step=2)
    monkeypatch.undo()
    assert os.listdir(tmp_path) == ["last.pt"]
    assert load_checkpoint(path)["step"] == 1
