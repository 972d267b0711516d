"""`cuboidgen masks`: a spool's samples as files anyone can fit, each input mask a PNG beside a JSON of its truth.

For trying `cuboidtrain infer` (and its error) on generated data without writing Python: the
PNG is the sample's input mask (`noisy`: occluded, contour noise; `clean=True`: the clean
silhouette), 0/255, at the spool's size; the JSON, of the same name, holds what was drawn, in
the infer record's terms and the mask's own pixels: `shape`, `keypoints` (pixel centres, the
contract's order) with their names, `ratios`, and the `camera` that framed it, a pinhole
camera's `focal_px` and `principal_px` (`shared.camera.Intrinsics.from_params`), as an infer
record's `cuboid` object gives a fitted one's (docs/contract.md). Files are named by the sample's
place in the spool's order, oldest first: `00000.png`, `00000.json`, ...
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from shared.camera import Intrinsics
from shared.errors import UsageError
from shared.files import atomic_path, write_json
from shared.sample import Sample, decode
from shared.shapes import get_shape
from shared.spool import check_spool, enumerate_spool, read_sample_bytes


def truth(sample: Sample, name: str, mask: str) -> dict:
    """The JSON beside a written mask: what the sample was drawn as, in its own pixels."""
    camera = Intrinsics.from_params(sample.params)
    return {"mask": mask, "sample": name, "shape": sample.shape, "size": sample.size, "seed": sample.seed,
            "keypoints": np.asarray(sample.keypoints).tolist(),
            "keypoint_names": list(get_shape(sample.shape).keypoint_names), "ratios": sample.ratios,
            "camera": {"focal_px": float(camera.focal), "principal_px": [float(v) for v in camera.principal]},
            "scene": sample.params.get("scene"), "occluded_fraction": sample.params.get("occluded_fraction")}


def write_masks(spool: Path, out: Path, count: int | None = None, clean: bool = False) -> int:
    """The first `count` samples of `spool` (all: None) as `out/NNNNN.png` and `out/NNNNN.json`, each
    replaced atomically; returns how many. Samples evicted meanwhile, or corrupt, are passed over."""
    if count is not None and count < 1:
        raise UsageError(f"--count {count}: expected at least 1 sample")
    spool = check_spool(spool, readable=True)
    written = 0
    for name in enumerate_spool(spool):
        if count is not None and written >= count:
            break
        data = read_sample_bytes(spool, name)
        try:
            sample = decode(data) if data is not None else None
        except ValueError:
            sample = None
        if sample is None:
            continue
        stem = f"{written:05d}"
        ok, png = cv2.imencode(".png", np.where(sample.clean if clean else sample.noisy, 255, 0).astype(np.uint8))
        if not ok:
            raise OSError(f"{out / stem}.png: cannot encode the mask")
        with atomic_path(out / f"{stem}.png") as tmp:  # makes `out` (and its parents) on the first
            tmp.write_bytes(png.tobytes())
        write_json(out / f"{stem}.json", truth(sample, name, f"{stem}.png"), indent=2)
        written += 1
    if not written:
        raise UsageError(f"spool {spool}: no decodable sample to write; expected a spool cuboidgen run filled")
    return written
