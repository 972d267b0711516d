"""ONNX export of the chain (CuboidNet.forward: R, K times, then S and T) and an onnxruntime runner.

The exported graph takes the model-resolution mask in +-1, float32 (B, 1, S, S),
with a dynamic batch axis, and gives `refined` (B, 1, S, S) tanh, `heatmaps`
(B, N, S, S), `keypoints` (B, N, 2) in model px and `ratios` (B, R). The K
Refiner passes are unrolled, each on the sign of the last (as
`cuboidtrain.models.refine.refine` with steps=K). The model's metadata_props say what the file is (format,
version, shape class, size, sigma, keypoint and ratio names, refine steps,
the source checkpoint's step); the runner checks them before it runs anything.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from cuboidtrain.models.checkpoint import load_model
from cuboidtrain.models.networks import CuboidNet
from cuboidtrain.fit.options import parse_refine_steps
from shared.errors import UsageError
from shared.files import atomic_path, json_text
from shared.shapes import get_shape

FORMAT = "cuboid-fit/onnx"
VERSION = 1
INPUT = "mask"
OUTPUTS = ("refined", "heatmaps", "keypoints", "ratios")
# Resize with half_pixel coordinates (F.interpolate, align_corners=False) needs opset 11;
# 20 is the newest opset torch 2.14's TorchScript-based exporter writes.
MIN_OPSET, MAX_OPSET, DEFAULT_OPSET = 11, 20, 17


class Pipeline(nn.Module):
    """CuboidNet.forward with K Refiner passes, tensor in, tensors out in OUTPUTS order (what a tracer takes)."""

    def __init__(self, model: CuboidNet, refine_steps: int):
        super().__init__()
        self.model, self.refine_steps = model, refine_steps

    def forward(self, mask: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.model(mask, self.refine_steps)  # a fixed K: a Python loop, unrolled into K copies of R
        return out.refined, out.heatmaps, out.keypoints, out.ratios


def check_options(refine_steps: int, opset: int) -> None:
    parse_refine_steps(refine_steps, allow_auto=False)  # a traced graph runs a fixed number of passes
    if not MIN_OPSET <= opset <= MAX_OPSET:
        raise UsageError(f"--opset {opset}: expected {MIN_OPSET} to {MAX_OPSET}")


def metadata(model: CuboidNet, sigma: float, refine_steps: int, step: int | None) -> dict[str, str]:
    """The file's metadata_props (ONNX keeps string values only: lists are JSON)."""
    geometry = get_shape(model.shape)
    return {
        "format": FORMAT, "version": str(VERSION), "shape": model.shape, "size": str(model.size), "arch": model.arch,
        "sigma": repr(float(sigma)), "keypoint_names": json_text(list(geometry.keypoint_names)),
        "ratio_names": json_text(list(geometry.ratio_names)), "refine_steps": str(refine_steps),
        "checkpoint_step": "" if step is None else str(step),
        # how to frame a mask for it: binary +-1, or each pixel's covered share onto [-1, 1]
        "input": "grey" if model.grey_input else "binary",
    }


def trace_to_onnx(model: CuboidNet, path: Path, refine_steps: int, opset: int) -> None:
    """torch.onnx.export through the TorchScript tracer (dynamo=False).

    Why not the default dynamo exporter: in torch 2.14.1 it needs `onnxscript`,
    another dependency, and our graph has no data-dependent control flow (the
    K passes unroll), which is what the tracer cannot handle; the traced graph
    matches eager to float rounding (tests/test_export.py).
    """
    example = torch.full((1, 1, model.size, model.size), -1.0)
    # The wrapper in eval mode too: the exporter restores the mode of the module it was
    # given afterwards, and a fresh (training) wrapper would leave the model's BN in training.
    pipeline = Pipeline(model, refine_steps).eval()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # the legacy exporter's deprecation and tracer notices
        torch.onnx.export(
            pipeline, (example,), str(path), dynamo=False, opset_version=opset,
            input_names=[INPUT], output_names=list(OUTPUTS), do_constant_folding=True,  # folds BN into convs
            dynamic_axes={name: {0: "batch"} for name in (INPUT, *OUTPUTS)},
        )


def export_model(model: CuboidNet, out: str | Path, sigma: float, refine_steps: int = 1,
                 opset: int = DEFAULT_OPSET, step: int | None = None) -> Path:
    """Write `out` (replaced atomically: a reader sees the old file or the new one), checked by onnx.checker."""
    import onnx

    check_options(refine_steps, opset)
    out = Path(out)
    with atomic_path(out) as tmp:
        trace_to_onnx(model, tmp, refine_steps, opset)
        proto = onnx.load(str(tmp))
        onnx.helper.set_model_props(proto, metadata(model, sigma, refine_steps, step))
        onnx.save(proto, str(tmp))
        onnx.checker.check_model(str(tmp))  # by path: also right for files past protobuf's 2 GB
    return out


def export_checkpoint(checkpoint: str | Path, out: str | Path, refine_steps: int = 1,
                      opset: int = DEFAULT_OPSET) -> dict[str, str]:
    """Export a trained checkpoint's whole pipeline; returns the metadata written."""
    check_options(refine_steps, opset)  # before the (slow) checkpoint load
    model, ckpt = load_model(checkpoint)
    export_model(model, out, ckpt["sigma"], refine_steps, opset, ckpt.get("step"))
    return read_metadata(out)


def read_metadata(path: str | Path) -> dict[str, str]:
    """metadata_props of an exported file, checked; ValueError (one line) on a foreign or broken file."""
    import onnx

    path = Path(path)
    if not path.is_file():
        raise UsageError(f"ONNX model {path}: no such file")
    try:
        proto = onnx.load(str(path), load_external_data=False)
    except Exception as exc:  # protobuf raises DecodeError, others for truncated files
        raise UsageError(f"ONNX model {path}: cannot read it ({type(exc).__name__})") from None
    props = {p.key: p.value for p in proto.metadata_props}
    check_metadata(path, props)
    return props


def check_metadata(path: Path, props: dict[str, str], shape: str | None = None, size: int | None = None) -> None:
    if props.get("format") != FORMAT:
        raise UsageError(f"ONNX model {path}: not a cuboid-fit export (format {props.get('format')!r}, "
                         f"expected {FORMAT!r})")
    if props.get("version") != str(VERSION):
        raise UsageError(f"ONNX model {path}: format version {props.get('version')!r}, expected {VERSION}")
    geometry = get_shape(props["shape"])
    if json.loads(props["keypoint_names"]) != list(geometry.keypoint_names):
        raise UsageError(f"ONNX model {path}: its {props['shape']} keypoint names differ from shared.shapes'")
    if shape is not None and props["shape"] != shape:
        raise UsageError(f"ONNX model {path}: a {props['shape']!r} model, expected {shape!r}")
    if size is not None and int(props["size"]) != size:
        raise UsageError(f"ONNX model {path}: a {props['size']} px model, expected {size} px")


def short(exc: Exception, limit: int = 240) -> str:
    """An onnxruntime error on one line; its reason is at the end, after a C++ signature."""
    text = " ".join(str(exc).split())
    return text if len(text) <= limit else "..." + text[-limit:]


class OnnxPipeline:
    """An exported file run with onnxruntime on the CPU: `run(mask)` -> OUTPUTS as numpy arrays.

    `threads` sets intra-op threads (None: onnxruntime's default, all cores);
    graph optimisation is `all` (fusions, constant folding, blocked layouts at
    load time). Worker threads do not spin between operators unless `spinning`:
    on a CPU shared with other jobs a spinning thread holds a core the others
    need. In bench_infer.py with 2 threads, spinning was 1.2-2.9x slower under
    load (load average 2.5-7) and 2-25% faster on a quiet machine; with 1 thread
    it was within 2% (BENCHMARKS.md). Pass spinning=True on a dedicated CPU. `shape`/`size`, when given, must match the metadata.
    """

    def __init__(self, path: str | Path, threads: int | None = None, shape: str | None = None,
                 size: int | None = None, spinning: bool = False):
        import onnxruntime as ort

        self.path = Path(path)
        if not self.path.is_file():
            raise UsageError(f"ONNX model {self.path}: no such file")
        if threads is not None and threads < 1:
            raise UsageError(f"threads {threads}: expected 1 or more")
        options = ort.SessionOptions()
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.intra_op_num_threads = threads or 0  # 0: onnxruntime picks (all cores)
        options.inter_op_num_threads = 1  # one chain, run in order: nothing to overlap
        options.log_severity_level = 3  # errors only: no warnings about unused initialisers
        options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
        try:
            self.session = ort.InferenceSession(str(self.path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # InvalidProtobuf, Fail, ... for a foreign or truncated file
            raise UsageError(f"ONNX model {self.path}: onnxruntime cannot load it ({short(exc)})") from None
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)
        check_metadata(self.path, self.metadata, shape, size)
        self.shape, self.size = self.metadata["shape"], int(self.metadata["size"])
        self.refine_steps = int(self.metadata["refine_steps"])

    def run(self, mask) -> dict[str, np.ndarray]:
        """(B, 1, S, S) +-1 mask (any real dtype; sent as float32) -> {refined, heatmaps, keypoints, ratios}."""
        mask = np.ascontiguousarray(mask, dtype=np.float32)
        if mask.ndim != 4 or mask.shape[1:] != (1, self.size, self.size) or mask.shape[0] < 1:
            raise ValueError(f"mask {tuple(mask.shape)}: expected (B, 1, {self.size}, {self.size}) for "
                             f"{self.path}")
        return dict(zip(OUTPUTS, self.session.run(list(OUTPUTS), {INPUT: mask})))
