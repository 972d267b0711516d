"""Draw docs/irregular.png: samples of the `irregular` scene, what each deviation added to the box's silhouette.

Each tile is a sample made by the generator itself (`cuboidgen.synth.make_sample` with the `irregular`
preset, seeds 0-11, box and twobox in turn): white where the noisy mask and the box's silhouette agree,
blue what the deviations added, red what occluders and the blurred edges took from the box; the
truth's corners in green; the title lists the sample's `deviations`.

    .venv/bin/python docs/irregular_figure.py [--out docs/irregular.png]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from cuboidgen.config import IRREGULAR  # noqa: E402
from cuboidgen.occluders import OccluderLibrary  # noqa: E402
from cuboidgen.synth import make_sample  # noqa: E402
from shared.files import save_figure  # noqa: E402

SIZE = 256
TILES = 12
ADDED, TAKEN, KEPT = (0.35, 0.6, 1.0), (1.0, 0.35, 0.35), (1.0, 1.0, 1.0)


def title(deviations: list[dict]) -> str:
    names = [d["kind"].replace("_", " ") + (f" ({d['style']})" if "style" in d else "") for d in deviations]
    lines = [", ".join(names[k : k + 3]) for k in range(0, len(names), 3)]  # three a line: the tiles are narrow
    return ",\n".join(lines) or "none"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "irregular.png")
    args = parser.parse_args()
    library = OccluderLibrary.load(None)
    fig, axes = plt.subplots(3, TILES // 3, figsize=(10, 9))
    for seed, ax in enumerate(axes.flat):
        sample = make_sample(("box", "twobox")[seed % 2], IRREGULAR, SIZE, seed, library)
        image = np.zeros((SIZE, SIZE, 3))
        image[sample.noisy & sample.clean] = KEPT
        image[sample.noisy & ~sample.clean] = ADDED
        image[sample.clean & ~sample.noisy] = TAKEN
        ax.imshow(image)
        ax.plot(*sample.keypoints.T, "o", color="#2ca02c", ms=3)
        ax.set_title(f"{sample.shape}\n{title(sample.params['deviations'])}", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    save_figure(fig, args.out, dpi=80)


if __name__ == "__main__":
    main()
