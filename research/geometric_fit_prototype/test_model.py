"""Step 1 check: the model reproduces the generator's keypoints and ratios for its own params."""
import sys
sys.path[:0] = ["/work/frozen", "/work/proto20"]
import numpy as np
from cuboidgen.config import SCENES
from cuboidgen.scene import draw_view
from shared.shapes import get_shape
import cuboid

worst = {}
for scene in ("paper", "paper-clean", "street"):
    for name in ("box", "twobox"):
        shape = get_shape(name)
        rng = np.random.default_rng(0)
        err = rerr = 0.0; flags = set()
        for _ in range(2000):
            v = draw_view(shape, SCENES[scene], 256, rng)
            cam = cuboid.from_generator(shape, v.params)
            err = max(err, np.abs(cam.keypoints() - v.keypoints).max())
            rerr = max(rerr, np.abs(cam.ratios() / shape.ratio_vector(v.ratios) - 1).max())
            named = cam.named_keypoints()
            assert np.abs(named - v.keypoints).max() < 1e-9, "viewer naming disagrees"
            flags.add((v.params["flip"], v.params["swap_left_right"], v.params["swap_front_back"], cam.mirror))
        print(f"{scene:12s} {name:7s} max px err {err:.2e}  max ratio rel err {rerr:.2e}  (flip,swapLR,swapFB,mirror) seen {len(flags)}")
