"""The lift of exact corners (`cuboidtrain.geometry.lift`): how often the generator's own
keypoints give back its corners (< 0.01 px) and ratios (< 0.1%), per scene and shape.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/accuracy/bench_lift.py --views 300

`paper-clean` has `paper`'s geometry (only mask noise differs), so it is not repeated.
"""
from __future__ import annotations

import argparse
import time
import numpy as np

from cuboidgen.config import SCENES
from cuboidgen.scene import draw_view
from cuboidtrain.geometry.lift import lift
from shared.shapes import get_shape


def measure(shape_name: str, scene: str, views: int, seed: int) -> dict:
    """Success rates and the median time of one lift, on `views` views drawn from `seed`."""
    shape, rng = get_shape(shape_name), np.random.default_rng(seed)
    both = corners_only = 0
    times = []
    for _ in range(views):
        view = draw_view(shape, SCENES[scene], 256, rng)
        start = time.perf_counter()
        camera = lift(view.keypoints, shape).camera
        times.append(time.perf_counter() - start)
        corners = np.abs(camera.named_keypoints() - view.keypoints).max() < 0.01
        ratios = np.abs(camera.ratios() / shape.ratio_vector(view.ratios) - 1).max() < 1e-3
        corners_only += corners
        both += corners and ratios
    return {"scene": scene, "shape": shape_name, "views": views, "recovered": both / views,
            "corners": corners_only / views, "ms_median": 1e3 * float(np.median(times))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--views", type=int, default=300)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    print("| scene | shape | views | corners < 0.01 px and ratios < 0.1% | corners < 0.01 px | ms median |")
    print("|---|---|---|---|---|---|")
    for scene in ("paper", "street"):
        for shape in ("box", "twobox"):
            r = measure(shape, scene, args.views, args.seed)
            print(f"| {scene} | {shape} | {r['views']} | {r['recovered']:.1%} | {r['corners']:.1%} | {r['ms_median']:.1f} |",
                  flush=True)


if __name__ == "__main__":
    main()
