"""The page's answer time against `infer`'s own time for the same mask (issue 41, Must have 6).

For each mask it times, medians of --repeats after one warm-up:

* infer's fit: `Fitter.outcomes([path])` with the shipped models, `cuboid=True`, one torch
  thread, in this process: what `cuboidtrain infer MASK --json OUT` spends on the mask, its
  imports and model loading left out (they are paid once, as the page's workers pay them);
* infer's fit with the page's outputs: the same with `infer --explain DIR --mesh DIR`'s writers
  (the explanation panel, the OBJ mesh), which the page's answer carries too;
* the page's answer: `cuboidtrain serve --workers 1` in a child process, an HTTP POST of the
  file's bytes to /api/fit?explain=0 until its JSON answer is read and parsed (the record, the
  mesh, the mask and the box in 3D: what the page shows first);
* the page's panel: the same POST with explain=1, which adds the explanation panel (the page
  asks for it second, and shows it when it comes).

The bar is the page's answer within infer's time plus 300 ms; the panel's request is compared
with infer's fit plus its writers.

    .venv/bin/python benchmarks/speed/bench_serve.py --repeats 7
"""
from __future__ import annotations

import argparse
import json
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BAR_MS = 300.0  # the page within infer's own time plus this


def median_ms(call, repeats: int) -> float:
    call()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append((time.perf_counter() - start) * 1000)
    return statistics.median(times)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def post(url: str, data: bytes) -> dict:
    request = urllib.request.Request(url, data=data, method="POST")
    with urllib.request.urlopen(request, timeout=120) as response:
        return json.loads(response.read())


def generated_mask(folder: Path) -> Path:
    """A 256 px twobox from the generator's `paper` scene (the page's "draw a generated one")."""
    from cuboidtrain.experiments.generated_mask import draw_generated

    path = folder / "twobox-256.png"
    path.write_bytes(draw_generated("twobox", "paper", 256, seed=5).png)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--masks", nargs="*", type=Path, default=None,
                        help="mask files (default: examples/building.png and a generated 256 px twobox)")
    args = parser.parse_args()

    import torch

    from cuboidtrain.fit.fitter import Fitter, Writers
    from cuboidtrain.fit.options import FitOptions
    from cuboidtrain.infer.explain import Explainer
    from cuboidtrain.infer.mesh import MeshWriter

    torch.set_num_threads(1)  # as the page's workers (and `infer --workers`) run
    work = Path(tempfile.mkdtemp(prefix="bench-serve-"))
    masks = args.masks or [ROOT / "examples" / "building.png", generated_mask(work)]
    options = FitOptions(cuboid=True, device="cpu")
    fitter = Fitter.from_shipped(options)
    port = free_port()
    server = subprocess.Popen([sys.executable, "-m", "cuboidtrain", "serve", "--port", str(port), "--workers", "1"],
                              stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        print(server.stdout.readline().strip(), file=sys.stderr)
        rows = []
        for mask in masks:
            data = mask.read_bytes()
            url = f"http://127.0.0.1:{port}/api/fit?name={mask.name}&explain="
            writers = Writers.of(Explainer(work / "explain"), MeshWriter(work / "mesh"))
            fit_ms = median_ms(lambda: fitter.outcomes([str(mask)]), args.repeats)
            drawn_ms = median_ms(lambda: fitter.outcomes([str(mask)], explain=writers), args.repeats)
            page_ms = median_ms(lambda: post(url + "0", data), args.repeats)
            panel_ms = median_ms(lambda: post(url + "1", data), args.repeats)
            rows.append((mask.name, fit_ms, page_ms, drawn_ms, panel_ms))
    finally:
        server.terminate()
        server.wait(30)
    print(f"{'mask':<16} {'infer fit':>10} {'page answer':>12} {'gap':>8} {'fit+panel+mesh':>15} {'page panel':>11} {'gap':>8}")
    for name, fit_ms, page_ms, drawn_ms, panel_ms in rows:
        print(f"{name:<16} {fit_ms:>7.0f} ms {page_ms:>9.0f} ms {page_ms - fit_ms:>5.0f} ms {drawn_ms:>12.0f} ms "
              f"{panel_ms:>8.0f} ms {panel_ms - drawn_ms:>5.0f} ms")
    print(f"medians of {args.repeats}; bar: the page's answer within infer's fit plus {BAR_MS:.0f} ms: "
          + ("held" if all(page - fit <= BAR_MS for _, fit, page, _, _ in rows) else "NOT held"))


if __name__ == "__main__":
    main()
