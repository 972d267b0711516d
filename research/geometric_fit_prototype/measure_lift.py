"""Step 2: lift exact named corners -> camera; success = all corners < 0.01 px and ratios < 0.1%.
Also the identifiability of the ratios at the truth: the least corner motion (L2 over all
coordinates, linearised) that a 0.1% change of depth/height or width/height costs."""
import sys, time, warnings
warnings.simplefilter("ignore")
sys.path[:0] = ["/work/frozen", "/work/proto20"]
import numpy as np
from cuboidgen.config import SCENES
from cuboidgen.scene import draw_view
from shared.shapes import get_shape
import cuboid


def ratio_cost_px(cam) -> float:
    p, h = cam.params, 1e-6
    base = cuboid.project(p, cam.shape, cam.mirror).ravel()
    jac = np.stack([(cuboid.project(p + h * e, cam.shape, cam.mirror).ravel() - base) / h for e in np.eye(len(p))], 1)
    cov = np.linalg.pinv(jac.T @ jac)
    return min(1e-3 / np.sqrt(cov[i, i]) for i in (0, 1))


n = int(sys.argv[1]) if len(sys.argv) > 1 else 500
print(f"| scene | shape | n | corners<0.01px & ratios<0.1% | corners<0.01px | median ratio err | ms/lift | views where 0.1% ratio costs <0.01 px |")
print("|---|---|---|---|---|---|---|---|")
for scene in ("paper", "paper-clean", "street"):
    for name in ("box", "twobox"):
        shape = get_shape(name)
        rng = np.random.default_rng(1)
        ok = okpx = 0; t = 0; rerrs = []; flat = 0; fails = []
        for i in range(n):
            v = draw_view(shape, SCENES[scene], 256, rng)
            t0 = time.perf_counter(); lifted = cuboid.lift(v.keypoints, shape); t += time.perf_counter() - t0
            px = np.abs(lifted.camera.keypoints() - v.keypoints).max()
            rr = np.abs(lifted.camera.ratios() / shape.ratio_vector(v.ratios) - 1).max()
            rerrs.append(rr); okpx += px < 0.01; ok += px < 0.01 and rr < 1e-3
            flat += ratio_cost_px(cuboid.from_generator(shape, v.params)) < 0.01
            if not (px < 0.01 and rr < 1e-3):
                fails.append(f"{i}:{px:.3g}px/{rr:.2g}")
        print(f"| {scene} | {name} | {n} | {ok / n:.1%} | {okpx / n:.1%} | {np.median(rerrs):.1e} | {1e3 * t / n:.1f} | {flat / n:.0%} |", flush=True)
        print("   fails:", " ".join(fails[:12]), file=sys.stderr, flush=True)
