"""The page's answer to one mask, made in a worker process by `cuboidtrain infer`'s own path.

An upload's bytes go to a file in a temporary folder under its own name; `Fitter.outcomes`
fits it with the page's FitOptions and `infer`'s writers, the explanation panel
(`infer.explain.Explainer`) and the OBJ mesh (`infer.mesh.MeshWriter`), write theirs beside it;
`records.to_records` makes the record. The answer carries the record, the panel, the mesh's
text and what the page draws (the mask the fit saw, the box in 3D), and the folder is deleted
before the answer leaves: nothing of an upload is kept. A bad input is the record's one-line
`error`, as `infer` writes it for a file of that name in the folder it runs in.

The worker holds the shipped models, loaded once (`start_worker`), and builds a `Fitter` of
them for each request's options, as `Fitter.from_shipped(options)` does from the same files.
"""
from __future__ import annotations

import base64
import contextlib
import logging
import math
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from cuboidtrain.fit.options import FitOptions
from cuboidtrain.infer.mesh import camera_box, depth_band
from shared.errors import UsageError
from shared.shapes import SHAPES, get_shape

MAX_DRAWN_GAP = 6.0  # box sizes: a box farther from its camera is drawn nearer (as the panel's 3D tile)
SAFE_NAME = re.compile(r"[^A-Za-z0-9._-]+")

_models: dict = {}  # shape class -> the shipped CuboidNet, loaded once a worker


@dataclass(frozen=True)
class PageRequest:
    """One mask to fit: its bytes and file name as uploaded, and the options (`FitOptions`, checked)."""

    data: bytes
    name: str
    options: FitOptions = field(default_factory=lambda: FitOptions(cuboid=True))
    # The explanation panel (`infer --explain`): matplotlib takes 1-3 s to draw it, 10-30 times the
    # fit, so the page asks for the answer without it first and for the panel in a second request.
    explain: bool = True


def start_worker() -> None:
    """A pool worker's start: one torch thread (as `infer --workers`), Ctrl-C left to the server,
    the shipped models and shape classifier loaded."""
    import torch

    from cuboidtrain.infer.stopping import leave_signals_to_parent
    from cuboidtrain.fit.shape_call import shipped_classifier
    from cuboidtrain.models.checkpoint import load_models
    from cuboidtrain.models.zoo import default_checkpoints

    leave_signals_to_parent()
    logging.basicConfig(level=logging.ERROR)  # a fit's warnings are in its record
    torch.set_num_threads(1)
    for model in load_models(default_checkpoints(None, SHAPES)):
        _models[model.shape] = model
    shipped_classifier()  # loaded (and its file checked) before the page says it is ready, as the models are


def ready() -> bool:
    """True once this worker holds its models (the server's warm-up waits on it)."""
    return bool(_models)


def safe_name(name: str) -> str:
    """The upload's file name without folders or characters a file name should not hold (`mask.png` if none)."""
    base = SAFE_NAME.sub("_", Path(name.replace("\\", "/")).name).strip("._")
    return base[:120] or "mask.png"


def fit_upload(request: PageRequest) -> dict:
    """The page's answer (JSON-ready) for one upload: `record`, `panel` (PNG, base64), `mesh` (OBJ
    text), `view` (the mask and the box in 3D), or the record alone with its `error`."""
    return answer_and_fit(request)[0]


def answer_and_fit(request: PageRequest):
    """`fit_upload`'s answer, and the Fit it was made from (None for an input that failed)."""
    from cuboidtrain.fit.fitter import Fitter, Writers
    from cuboidtrain.infer.explain import Explainer
    from cuboidtrain.infer.mesh import MeshWriter
    from cuboidtrain.infer.records import to_records

    options = request.options.validate()
    name = safe_name(request.name)
    fitter = Fitter([_models[s] for s in options.shapes], options)
    # In the upload's own folder, fitted by its name: the record, an error, the panel and the mesh
    # name it as `cuboidtrain infer NAME` run there does. A worker fits one mask at a time.
    with tempfile.TemporaryDirectory(prefix="cuboid-page-") as folder, contextlib.chdir(folder):
        Path(name).write_bytes(request.data)
        view = ViewCapture()
        mesher = MeshWriter(Path(".mesh"))  # no upload's name starts with "."
        explainer = Explainer(Path(".explain")) if request.explain else None
        outcomes = fitter.outcomes([name], explain=Writers.of(view, explainer, mesher))
        [record] = to_records(outcomes[:1], options)
        answer = {"record": record, "panel": None, "mesh": None, "view": view.view}
        if record["error"] is None:
            answer["panel"] = read_b64(explainer.written[0]) if explainer is not None and explainer.written else None
            answer["mesh"] = mesher.written[0].read_text(encoding="utf-8") if mesher.written else None
    return answer, (outcomes[0] if record["error"] is None else None)


def read_b64(path: Path) -> str:
    return base64.b64encode(path.read_bytes()).decode("ascii")


class ViewCapture:
    """A per-fit writer (`Fitter.outcomes`'s callback) that keeps what the page draws of the fit
    while its explanation's arrays are at hand: the mask the fit saw and the box in 3D."""

    def __init__(self):
        self.view: dict | None = None

    def __call__(self, index: int, path: str, fit) -> tuple[str, ...]:
        if self.view is None:
            self.view = page_view(fit)
        return ()


def page_view(fit) -> dict:
    """The mask the fit saw (PNG, base64), its size, the wireframe's edges and the box in 3D."""
    mask = fit.explanation.mask
    ok, png = cv2.imencode(".png", np.where(mask, 255, 0).astype(np.uint8))
    shape = get_shape(fit.shape)
    return {"mask": base64.b64encode(png.tobytes()).decode("ascii") if ok else None,
            "width": int(mask.shape[1]), "height": int(mask.shape[0]),
            "edges": [list(map(int, e)) for e in shape.edges], "front": shape.having("FRONT").tolist(),
            "names": list(shape.keypoint_names), "box3d": box_view(fit) if fit.cuboid is not None else None}


def box_view(fit) -> dict:
    """The fitted box in its camera's frame (x right, y down, z forward; units: box heights), drawn
    nearer when far as the panel's 3D tile draws it, its faces, and its depth's one-sd band."""
    box = camera_box(fit.cuboid.fit)
    corners = box.corners
    centre = corners.mean(axis=0)
    distance, size = float(np.linalg.norm(centre)), float(np.ptp(corners, axis=0).max())
    nearer = MAX_DRAWN_GAP * size / distance if distance > MAX_DRAWN_GAP * size else 1.0
    drawn = corners - centre + centre * nearer
    band = depth_band(type(box)(box.shape, drawn, box.focal, box.principal, box.nominal), fit.ratios,
                      fit.cuboid.fit.spread)
    return {"corners": drawn.tolist(), "faces": [[part, face, list(map(int, quad))] for part, quads in box.faces()
                                                 for face, quad in quads],
            "focal": box.focal * nearer, "principal": list(box.principal), "nominal": bool(box.nominal),
            "nearer": nearer, "distance": distance,
            "band": None if band is None else {"sd_log": band[0], "factor": math.exp(band[0]),
                                               "shallower": band[1].tolist(), "deeper": band[2].tolist()}}


def fit_generated(shape: str, scene: str, size: int, seed: int, options: FitOptions, explain: bool = True) -> dict:
    """A generated mask (`experiments.generated_mask`) fitted as an upload, with its truth and the
    fit's errors against it (`geometry.accuracy.against_truth`)."""
    from cuboidtrain.experiments.generated_mask import draw_generated

    drawn = draw_generated(shape, scene, size, seed)
    answer, fit = answer_and_fit(PageRequest(drawn.png, drawn.truth["mask"], options, explain))
    answer["truth"] = drawn.truth
    if fit is not None:
        answer["errors"] = truth_errors(fit, drawn.scored)
    return answer


def truth_errors(fit, truth) -> dict:
    """A fit against the truth it was drawn from, as the accuracy benchmarks score it: corner errors
    (px, hull and interior), relative ratio errors, and the yaw (deg) and 3D IoU of its cuboid."""
    from cuboidtrain.geometry.accuracy import against_truth

    if fit.shape != truth.shape.name:
        return {"mismatch": f"fitted a {fit.shape}, drawn a {truth.shape.name}: no corner-by-corner errors"}
    camera = fit.cuboid.fit.camera if fit.cuboid is not None else None
    scored = against_truth(np.asarray(fit.keypoints), fit.ratios, truth, camera)
    corners = np.concatenate([scored.hull, scored.interior])
    finite = lambda v: None if v is None or not math.isfinite(v) else float(v)  # noqa: E731
    return {"mean_corner_px": float(corners.mean()), "hull_px": float(scored.hull.mean()) if scored.hull.size else None,
            "interior_px": float(scored.interior.mean()) if scored.interior.size else None,
            "depth_height": [float(v) for v in scored.depth_height], "width_height": [float(v) for v in scored.width_height],
            "yaw_deg": finite(scored.yaw_deg), "iou3d": finite(scored.iou3d)}
