"""Inference latency per mask, batch 1, CPU: torch eager against onnxruntime on the exported graph.

For each size it times R (one pass), S and T on one +-1 mask: torch eager
(model.eval(), torch.inference_mode) and onnxruntime (the `cuboidtrain export`
graph, graph optimisation `all`, --threads intra-op threads), in one process,
interleaved call by call so that both see the same load. The ratio is
onnxruntime's median over eager's. For context it also times the whole
`infer_paths` on a PNG file (read, components, framing, R+S+T, confidence, the
record), torch eager. Random weights unless --checkpoint (the same arithmetic).
`--variants` adds speed-ups that keep the outputs: channels_last eager, frozen
TorchScript (BN folded), onnxruntime with basic optimisation only, and with
spinning worker threads (onnxruntime's default; OnnxPipeline turns it off).

`--records N` times instead what a user waits for: the whole `infer` record of one 256 px
PNG with the shipped models, both shape classes tried, networks only against `--cuboid`
(the cuboid fit to the mask: issue 20's bar is 50 ms median on one thread), interleaved
mask by mask over N generated masks (box and twobox, `paper-clean`, `paper`, `street`).

    .venv/bin/python benchmarks/speed/bench_infer.py --sizes 64 128 256 --threads 2 --repeats 30
    .venv/bin/python benchmarks/speed/bench_infer.py --records 60 --threads 1 --repeats 5
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from cuboidgen.config import PAPER, SCENES
from cuboidgen.occluders import OccluderLibrary
from cuboidgen.synth import make_sample
from cuboidtrain.models.checkpoint import load_model
from cuboidtrain.models.codec import default_sigma
from cuboidtrain.infer.export import OnnxPipeline, Pipeline, export_model
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.models.networks import build_model
from cuboidtrain.fit.options import FitOptions
from shared.sample import signed

TARGET_MS = 150.0  # docs/contract.md, "Targets": R+S+T at 256x256, batch 1, 2-core CPU
CUBOID_TARGET_MS = 50.0  # issue 20, Must have 9: the whole --cuboid record, both shape classes, one thread


def median_ms(call, repeats: int, warmup: int) -> float:
    for _ in range(warmup):
        call()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return 1000 * statistics.median(times)


def interleaved_ms(calls: dict, repeats: int, warmup: int) -> dict[str, float]:
    """Median ms per call of each runner, timed in turn (a, b, a, b, ...) so load spikes hit both."""
    for call in calls.values():
        for _ in range(warmup):
            call()
    times = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    return {name: 1000 * statistics.median(t) for name, t in times.items()}


def sample_mask(shape: str, size: int, seed: int = 0) -> np.ndarray:
    """A generated noisy, occluded silhouette: bool (size, size)."""
    return make_sample(shape, PAPER, size, seed, OccluderLibrary.builtin(variants_per_kind=2, seed=0)).noisy


def runners(model, onnx_path: Path, mask: np.ndarray, threads: int) -> dict:
    """The two contenders: torch eager and onnxruntime (OnnxPipeline: graph optimisation all, no spinning)."""
    x = torch.from_numpy(signed(mask)[None, None])
    session, feed = OnnxPipeline(onnx_path, threads=threads), x.numpy()

    def eager():
        with torch.inference_mode():
            return model(x)

    return {"eager": eager, "onnxruntime": lambda: session.run(feed)}


def variant_runners(model, onnx_path: Path, mask: np.ndarray, threads: int) -> dict:
    """Speed-ups that keep the outputs (to float rounding), tried against the two above."""
    import onnxruntime as ort

    x = torch.from_numpy(signed(mask)[None, None])
    feed = {"mask": x.numpy()}
    channels_last = copy.deepcopy(model).to(memory_format=torch.channels_last)
    x_cl = x.contiguous(memory_format=torch.channels_last)
    with torch.inference_mode(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the tracer's notes
        traced = torch.jit.trace(Pipeline(model, 1).eval(), x)
        frozen = torch.jit.optimize_for_inference(torch.jit.freeze(traced))  # BN folded, MKLDNN where it pays

    def session(level):
        options = ort.SessionOptions()
        options.graph_optimization_level, options.intra_op_num_threads, options.inter_op_num_threads = level, threads, 1
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")  # as OnnxPipeline
        return ort.InferenceSession(str(onnx_path), options, providers=["CPUExecutionProvider"])

    basic = session(ort.GraphOptimizationLevel.ORT_ENABLE_BASIC)
    spinning = OnnxPipeline(onnx_path, threads=threads, spinning=True)  # onnxruntime's own default

    def inference(call):
        def run():
            with torch.inference_mode():
                return call()
        return run

    return {"eager_channels_last": inference(lambda: channels_last(x_cl)),
            "torchscript_frozen": inference(lambda: frozen(x)),
            "onnxruntime_basic_opt": lambda: basic.run(None, feed),
            "onnxruntime_spinning": lambda: spinning.run(feed["mask"])}


def bench_size(model, size: int, threads: int, repeats: int, warmup: int, folder: Path, variants: bool) -> dict:
    """R+S+T eager vs onnxruntime (and the variants), and infer_paths on a PNG, at one size."""
    onnx_path = export_model(model, folder / f"{model.shape}-{size}.onnx", default_sigma(size), refine_steps=1)
    mask = sample_mask(model.shape, size)
    calls = runners(model, onnx_path, mask, threads)
    if variants:
        calls |= variant_runners(model, onnx_path, mask, threads)
    ms = interleaved_ms(calls, repeats, warmup)
    # A "photo-sized" mask for infer_paths: 1.5x the model size, so framing really resizes.
    png = folder / f"mask-{size}.png"
    big = cv2.resize(mask.astype(np.uint8) * 255, (size * 3 // 2, size * 3 // 2), interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(png), big)
    end_to_end = median_ms(lambda: Fitter([model], FitOptions(shape=model.shape, device="cpu")).outcomes([png]),
                           max(3, repeats // 3), 1)
    return {"shape": model.shape, "size": size, "eager_ms": ms["eager"], "onnxruntime_ms": ms["onnxruntime"],
            "onnxruntime_vs_eager": ms["onnxruntime"] / ms["eager"], "infer_paths_eager_ms": end_to_end,
            "onnx_mb": onnx_path.stat().st_size / 2**20,
            "variants_ms": {name: value for name, value in ms.items() if name not in ("eager", "onnxruntime")}}


def record_masks(count: int, folder: Path) -> list[Path]:
    """`count` generated 256 px noisy masks as PNGs, cycling through box and twobox in each scene."""
    library = OccluderLibrary.builtin(variants_per_kind=2, seed=0)
    kinds = [(shape, scene) for scene in ("paper-clean", "paper", "street") for shape in ("box", "twobox")]
    paths = []
    for index in range(count):
        shape, scene = kinds[index % len(kinds)]
        path = folder / f"record-{index:03d}-{scene}-{shape}.png"
        cv2.imwrite(str(path), make_sample(shape, SCENES[scene], 256, 1000 + index, library).noisy.astype(np.uint8) * 255)
        paths.append(path)
    return paths


def bench_records(count: int, repeats: int, folder: Path) -> dict:
    """Median ms of the whole record (`Fitter.outcomes` of one PNG), networks only and `--cuboid`,
    timed in turn on each mask (so load spikes hit both), `repeats` times over `count` masks."""
    paths = record_masks(count, folder)
    fitters = {"networks": Fitter.from_shipped(FitOptions(device="cpu")),
               "cuboid": Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))}
    times = {name: [] for name in fitters}
    for fitter in fitters.values():  # warm-up: first calls allocate
        fitter.outcomes(paths[:2])
    for _ in range(repeats):
        for path in paths:
            for name, fitter in fitters.items():
                start = time.perf_counter()
                fitter.outcomes([path])
                times[name].append(time.perf_counter() - start)
    medians = {name: 1000 * statistics.median(t) for name, t in times.items()}
    return {"masks": count, "repeats": repeats, "networks_ms": medians["networks"], "cuboid_ms": medians["cuboid"],
            "cuboid_p90_ms": 1000 * float(np.percentile(times["cuboid"], 90)),
            "cuboid_vs_networks": medians["cuboid"] / medians["networks"], "cuboid_target_ms": CUBOID_TARGET_MS}


def records_table(row: dict, threads: int) -> Table:
    t = Table(title=f"the whole infer record, shipped models, both shape classes, {threads} thread(s): "
                    f"median over {row['masks']} masks x {row['repeats']}")
    for col in ("networks only", "--cuboid", "--cuboid p90", "ratio", f"<= {CUBOID_TARGET_MS:.0f}"):
        t.add_column(col, justify="right")
    t.add_row(f"{row['networks_ms']:.1f}", f"{row['cuboid_ms']:.1f}", f"{row['cuboid_p90_ms']:.1f}",
              f"{row['cuboid_vs_networks']:.2f}", "yes" if row["cuboid_ms"] <= CUBOID_TARGET_MS else "no")
    return t


SHORT = {"eager_channels_last": "eager CL", "torchscript_frozen": "TS frozen",
         "onnxruntime_basic_opt": "ort basic", "onnxruntime_spinning": "ort spinning"}


def table(rows: list[dict], threads: int) -> Table:
    t = Table(title=f"ms per mask (medians), batch 1, {threads} thread(s); ort = onnxruntime, opt all, no spinning")
    variants = list(rows[0]["variants_ms"]) if rows else []
    for col in ("shape", "size", "eager", "ort", "ort/eager", *[SHORT[v] for v in variants], "infer_paths",
                "<=150 at 256"):
        t.add_column(col, justify="right")
    for r in rows:
        best = min(r["eager_ms"], r["onnxruntime_ms"], *r["variants_ms"].values())
        verdict = ("yes" if best <= TARGET_MS else "no") if r["size"] == 256 else ""
        t.add_row(r["shape"], str(r["size"]), f"{r['eager_ms']:.1f}", f"{r['onnxruntime_ms']:.1f}",
                  f"{r['onnxruntime_vs_eager']:.2f}", *[f"{r['variants_ms'][v]:.1f}" for v in variants],
                  f"{r['infer_paths_eager_ms']:.1f}", verdict)
    return t


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--shape", default="box", help="box or twobox (random weights).")
    parser.add_argument("--checkpoint", type=Path, default=None, help="A trained model instead (its size only).")
    parser.add_argument("--threads", type=int, default=2, help="torch and onnxruntime intra-op threads.")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--variants", action="store_true",
                        help="Also time channels_last eager, frozen TorchScript, onnxruntime basic opt / spinning.")
    parser.add_argument("--records", type=int, default=0, metavar="N",
                        help="Time the whole infer record instead, networks only vs --cuboid, over N masks.")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    if args.records:
        with tempfile.TemporaryDirectory() as tmp:
            row = bench_records(args.records, args.repeats, Path(tmp))
        result = {"threads": args.threads, "torch": torch.__version__, "cpus": os.cpu_count(),
                  "loadavg_before": load_before, "loadavg_after": os.getloadavg(), "records": row}
        Console(width=150).print(records_table(row, args.threads))
        print(json.dumps(result))
        if args.json:
            args.json.write_text(json.dumps(result, indent=2))
        return
    if args.checkpoint:
        model, _ = load_model(args.checkpoint)
        models = [model]
    else:
        models = [build_model(args.shape, size).eval() for size in args.sizes]
    with tempfile.TemporaryDirectory() as tmp:
        rows = [bench_size(m, m.size, args.threads, args.repeats, args.warmup, Path(tmp), args.variants)
                for m in models]
    result = {"threads": args.threads, "repeats": args.repeats, "torch": torch.__version__,
              "onnxruntime": __import__("onnxruntime").__version__, "cpus": os.cpu_count(),
              "loadavg_before": load_before, "loadavg_after": os.getloadavg(), "rows": rows}
    Console(width=150).print(table(rows, args.threads))  # the whole table, also into a pipe
    print(json.dumps(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
