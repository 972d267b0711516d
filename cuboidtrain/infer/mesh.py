"""`cuboidtrain infer --cuboid --mesh DIR`: each fitted box as a Wavefront OBJ file, in the camera's frame.

A `--cuboid` fit is a perspective box (or two) before a pinhole camera (cuboidtrain.fit.cuboid,
cuboidtrain.geometry.camera_params); `camera_box` gives its corners in that camera's frame and this module
writes them as a mesh that common viewers open (Blender, MeshLab, any OBJ reader):

* **Frame**: OpenCV's camera at the origin: x right, y down, z forward (the way it looks), so the
  box is where the fitted camera sees it. **Units**: the height of the box (of a twobox's taller
  part) is 1; a mask fixes the box only up to scale.
* **Vertices**: the record's keypoints, in its order: OBJ vertex k + 1 is keypoint k, and
  projects onto it, u = focal * x / z + principal (to float64 rounding).
* **Objects**: one `o` per part (`box`; a twobox's `right` and `left`, which share the two
  vertices of their common wall's bottom edge), six quads each, named in a comment line before each (FRONT, ...),
  wound counter-clockwise seen from outside: outward normals by the right-hand rule.
* **Header comments**: the input, shape, the camera's focal length and principal point in input
  px, and the input's size: what a viewer needs to put the camera back.
* **Weak perspective** (a fit with no finite focal length: the record's `focal_px` is null): the
  box is placed at `NOMINAL_DISTANCE` box heights and the header says so; with the focal length
  that distance implies, its projection is the fit's to within about (the box's depth in the
  view / NOMINAL_DISTANCE) of its image size: 0.1% for a box as deep as it is high.

The files are named like `--explain`'s panels (`cuboidtrain.infer.inputs.OutputNames`): `<stem>.obj`,
`<stem>-<component>.obj` with `--all-components`, written atomically. No matplotlib, no torch:
it also runs in `--workers` processes.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cuboidtrain.geometry.camera_params import CuboidFit
from cuboidtrain.infer.inputs import OutputNames
from shared.errors import UsageError
from shared.files import atomic_path
from shared.shapes import Shape, get_shape

if TYPE_CHECKING:
    from cuboidtrain.fit.fitter import Fit

log = logging.getLogger(__name__)

NOMINAL_DISTANCE = 1000.0  # box heights: where a weak-perspective fit's box is put
# Table 1 corner c = 4 * front + 2 * left + bottom: a face fixes one bit, (bit, value) -> its name.
FACES = {(4, 1): "FRONT", (4, 0): "BACK", (2, 1): "LEFT", (2, 0): "RIGHT", (1, 1): "BOTTOM", (1, 0): "TOP"}


@dataclass(frozen=True)
class CameraBox:
    """A fitted cuboid in its camera's frame (see the module's docstring)."""

    shape: Shape
    corners: np.ndarray  # (N, 3) camera frame, box heights, in the record's keypoint order
    focal: float  # px
    principal: tuple[float, float]  # px
    nominal: bool  # weak perspective: placed at NOMINAL_DISTANCE, not at a fitted distance

    def project(self) -> np.ndarray:
        """(N, 2) px: the corners through the pinhole camera."""
        return self.corners[:, :2] / self.corners[:, 2:3] * self.focal + np.asarray(self.principal)

    def faces(self) -> list[tuple[str, list[tuple[str, tuple[int, int, int, int]]]]]:
        """Per part (name, its six (face name, four keypoint indices)), each quad counter-clockwise
        seen from outside the part."""
        parts = []
        for name, part in zip(self.shape.part_names, self.shape.parts):
            centre = self.corners[list(part)].mean(axis=0)
            quads = []
            for (bit, value), face in FACES.items():
                a, b = [q for q in (1, 2, 4) if q != bit]
                cycle = [part[value * bit + i * a + j * b] for i, j in ((0, 0), (1, 0), (1, 1), (0, 1))]
                points = self.corners[cycle]
                normal = np.cross(points[1] - points[0], points[2] - points[0]) + np.cross(
                    points[2] - points[0], points[3] - points[0])
                if normal @ (points.mean(axis=0) - centre) < 0:
                    cycle.reverse()
                quads.append((face, tuple(cycle)))
            parts.append((name, quads))
        return parts


def camera_box(fit: CuboidFit) -> CameraBox:
    """The fitted cuboid's corners in the camera's frame, named as `fit.keypoints`.

    The fit's projection is u = c + s (R X + t)_xy / (1 + k (R X)_z) (geometry's layout), the
    pinhole u = c + f P_xy / P_z with P = R X + (tx, ty, 1/k) and f = s / k; k = 0 (weak
    perspective) takes 1/k = NOMINAL_DISTANCE instead."""
    camera = fit.camera
    shape, p = camera.shape, camera.vector
    nominal = camera.weak
    points = camera.camera_points(NOMINAL_DISTANCE if nominal else None)
    scale = 1.0 if len(shape.parts) == 1 else max(1.0, math.exp(p[12]))  # the taller part is 1 high
    # The same expression as CameraParams.pinhole's, so the header's focal length is the record's to the last bit.
    focal = math.exp(p[7]) * NOMINAL_DISTANCE if nominal else math.exp(p[7]) / p[8]
    return CameraBox(shape=shape, corners=points[camera.naming()] / scale, focal=float(focal),
                     principal=(float(p[9]), float(p[10])), nominal=nominal)


def depth_band(box: CameraBox, ratios: dict, spread) -> tuple[float, np.ndarray, np.ndarray] | None:
    """The box at minus and plus one sd of its depth: (s, shallower (N, 3), deeper (N, 3)), `box.corners`
    scaled about the box's centre along its depth axis by exp(-s) and exp(+s), s the sd of log depth
    (the error bars' own scale, `spread.ratios[0]` over depth/height), so a wide band stays a box (never
    a negative depth). None without error bars (`spread` None). The panel's 3D tile and the page draw it."""
    if spread is None:
        return None
    relative = float(spread.ratios[0] / box.shape.ratio_vector(ratios)[0])
    front, back = box.shape.having("FRONT"), box.shape.having("BACK")
    axis = box.corners[back].mean(axis=0) - box.corners[front].mean(axis=0)  # FRONT -> BACK, one depth long
    side = np.zeros(len(box.corners))
    side[back], side[front] = 0.5, -0.5
    shallower, deeper = ((box.corners + (math.exp(sign * relative) - 1.0) * side[:, None] * axis) for sign in (-1.0, 1.0))
    return relative, shallower, deeper


def obj_text(box: CameraBox, header: Sequence[str] = ()) -> str:
    """The OBJ file's text: `header` lines as comments, the camera, the vertices, the faces (numbers written
    exactly: repr of a float64)."""
    lines = [f"# {line}" for line in header]
    lines += ["# camera: OpenCV's at the origin, x right, y down, z forward; units: box heights (up to scale)",
              f"# focal_px {box.focal!r} principal_px {box.principal[0]!r} {box.principal[1]!r}"
              + (f" (weak perspective: placed at a nominal {NOMINAL_DISTANCE:g} box heights)" if box.nominal else ""),
              "# vertex k + 1 is keypoint k: " + ", ".join(box.shape.keypoint_names)]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in box.corners.tolist()]
    for name, quads in box.faces():
        lines.append(f"o {name}")
        for face, cycle in quads:  # the name on a line of its own: not every reader takes a comment after data
            lines += [f"# {face}", f"f {' '.join(str(i + 1) for i in cycle)}"]
    return "\n".join(lines) + "\n"


def read_obj(path: Path) -> tuple[np.ndarray, dict[str, list[tuple[int, ...]]]]:
    """(vertices (V, 3), {object: faces as 0-based index tuples}) of an OBJ file of `v`, `o` and `f`
    lines (what `obj_text` writes; comments and other lines are skipped)."""
    vertices, objects, current = [], {}, None
    for line in Path(path).read_text(encoding="utf-8").splitlines():
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        if words[0] == "v":
            vertices.append([float(w) for w in words[1:4]])
        elif words[0] == "o":
            current = " ".join(words[1:])
            objects[current] = []
        elif words[0] == "f":
            objects.setdefault(current, []).append(tuple(int(w.split("/")[0]) - 1 for w in words[1:]))
    return np.array(vertices, dtype=np.float64).reshape(-1, 3), objects


class MeshWriter:
    """`Fitter.outcomes`'s per-fit callback for `--mesh DIR`: writes each fitted cuboid to `folder`.

    `inputs` (the run's inputs, in index order) fixes the file names whichever process writes
    them; without it, names are given in the order fits arrive (`OutputNames`)."""

    def __init__(self, folder: Path, inputs: Sequence[str] | None = None):
        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise UsageError(f"--mesh {self.folder}: not a folder")
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UsageError(f"--mesh {self.folder}: cannot make the folder ({exc.strerror or exc})") from None
        self.names = OutputNames(inputs)
        self.written: list[Path] = []

    def __call__(self, index: int, path: str, fit: Fit) -> tuple[str, ...]:
        """Write `fit`'s box (input `index`, file `path`); the warning for its record when it cannot."""
        if fit.cuboid is None:
            return ("no mesh: the fit has no cuboid (fit with --cuboid)",)
        stem = self.names(index, path) + (f"-{fit.component}" if fit.component is not None else "")
        target = self.folder / f"{stem}.obj"
        try:
            box = camera_box(fit.cuboid.fit)
            height, width = fit.explanation.mask.shape if fit.explanation is not None else (None, None)
            header = [f"cuboidtrain infer --cuboid --mesh: {fit.shape} fitted to {path}"
                      + (f" (component {fit.component})" if fit.component is not None else ""),
                      *([f"input {width} x {height} px"] if width is not None else []), *uncertainty(fit)]
            text = obj_text(box, header)
            with atomic_path(target) as tmp:  # a reader never sees half a mesh
                Path(tmp).write_text(text, encoding="utf-8")
        except (OSError, ValueError) as exc:  # a full disk, an unwritable folder
            warning = "no mesh: " + " ".join(str(exc).split())
            log.warning("%s: %s", path, warning)
            return (warning,)
        self.written.append(target)
        return ()


def check_mesh_options(mesh: Path | None, cuboid: bool, cluster: str | None) -> None:
    """`--mesh DIR` needs the cuboid fit (a mesh is the fitted 3D box; the networks alone give 2D points)
    and runs in this process or `--workers`, not on a cluster; one-line UsageErrors."""
    if mesh is None:
        return
    if not cuboid:
        raise UsageError(f"--mesh {mesh} with --networks-only: expected the cuboid fit (the mesh is the fitted 3D "
                         f"box; the networks alone give only image points)")
    if cluster is not None:
        raise UsageError(f"--mesh with --cluster {cluster}: expected no --cluster (meshes are written by the "
                         f"process that fits; use --workers)")


def uncertainty(fit: Fit) -> list[str]:
    """The header's lines on how far to trust the box: each ratio with its sd, which intrinsics
    were given (docs/contract.md, "Error bars")."""
    sd = fit.cuboid.ratios_sd()
    lines = [f"intrinsics: focal_px {fit.cuboid.source('focal_px')}, principal_px {fit.cuboid.source('principal_px')}"]
    if sd is not None:
        shape = get_shape(fit.shape)
        lines.append("ratios +- sd: " + ", ".join(f"{name} {value:.3f} +- {spread:.3f}" for name, value, spread in zip(
            shape.ratio_names, shape.ratio_vector(fit.ratios), shape.ratio_vector(sd))))
    return lines
