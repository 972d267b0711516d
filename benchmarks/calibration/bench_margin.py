"""Shape selection against the richer class's margin (`fit.cuboid.CUBOID_MARGIN`), through `Fitter.fit`.

For each set (`paper`, `street`, `paper-clean`) and shape class, masks --offset .. --offset +
--samples of bench_accuracy's seeded 256 px spools are fitted by the shipped models with each
margin in turn, and the masks given their own class are counted; the twobox's IoU less the box's
(`Fit.candidates`) is summarised at the shipped margin.

    .venv/bin/python benchmarks/calibration/bench_margin.py --samples 40 --offset 80
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parent.parent / "accuracy")]
import cuboidtrain.fit.cuboid as stage  # noqa: E402
from bench_accuracy import spool_for  # noqa: E402
from cuboidtrain.fit.fitter import Fitter  # noqa: E402
from cuboidtrain.fit.options import FitOptions  # noqa: E402
from shared.sample import decode  # noqa: E402
from shared.spool import enumerate_spool, read_sample_bytes  # noqa: E402

MARGINS = (0.005, 0.01, 0.02)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=40)
    parser.add_argument("--offset", type=int, default=80)
    parser.add_argument("--spools", type=Path, default=Path("bench-spools"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    fitter, shipped = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True)), stage.CUBOID_MARGIN
    for scene in ("paper", "street", "paper-clean"):
        for shape in ("box", "twobox"):
            spool = spool_for(args.spools, shape, scene, args.offset + args.samples)
            masks = [decode(read_sample_bytes(spool, name)).noisy.astype(np.uint8) * 255
                     for name in enumerate_spool(spool)[args.offset : args.offset + args.samples]]
            right = {}
            for margin in MARGINS:
                stage.CUBOID_MARGIN = margin  # read by choose_cuboid at each call
                fits = [fitter.fit(mask) for mask in masks]
                right[margin] = sum(f.shape == shape for f in fits)
                if margin == shipped:
                    gaps = np.array([f.candidates["twobox"] - f.candidates["box"] for f in fits])
            stage.CUBOID_MARGIN = shipped
            print(f"{scene} {shape}: right of {len(masks)} by margin {right}; twobox IoU - box IoU "
                  f"median {np.median(gaps):.4f}, 95th percentile {np.percentile(gaps, 95):.4f}", flush=True)


if __name__ == "__main__":
    main()
