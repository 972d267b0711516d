"""Irregular buildings: what real outlines show beside the box (the `irregular` scene).

A segmented building is seldom its box: a roof line stands on top (pitched or a set-back storey),
a chimney or a parapet, a neighbour's corner is merged into one side, the segmentation's edges are
blobby and its resolution low. `draw_deviations` draws which of these a sample gets, and their
sizes, from the scene's probabilities and ranges; `with_structures` adds the solid ones to the
silhouette, each a convex solid in the box's own frame projected by the sample's camera (so it
keeps the view's perspective); `degrade` blurs the outline as a segmentation network does.

The truth is untouched: the keypoints, ratios and clean silhouette stay the box's (or twobox's),
so the Refiner is trained to remove what is not the box, and a fit is scored against the box.
Each deviation is a plain dict (`kind` and its numbers) recorded in the sample's `params`.
"""
from __future__ import annotations

import cv2
import numpy as np

from cuboidgen.config import SceneConfig
from cuboidgen.noise import roughen
from cuboidgen.scene import View, uniform
from shared.camera import Intrinsics, project
from shared.raster import fill_convex
from shared.shapes import Shape

SOLIDS = ("roof", "chimney", "parapet", "neighbour")  # added to the silhouette before occlusion
BLURS = ("blob", "low_res")  # applied to the noisy mask last
NEAREST_DEPTH = 0.5  # a solid with a vertex nearer the camera than this share of the building's nearest corner is left out
PARAPET_THICKNESS = 0.03  # of the part's depth or width: a wall, seen as its height


def irregular(scene: SceneConfig) -> bool:
    """Whether `scene` draws any deviation (every other scene's samples stay bit for bit as they were)."""
    return any(getattr(scene, f"{kind}_probability") > 0 for kind in (*SOLIDS, *BLURS))


def draw_deviations(shape: Shape, scene: SceneConfig, rng: np.random.Generator) -> list[dict]:
    """Which deviations one sample gets, with their numbers, in a fixed order (roof, chimney, parapet,
    neighbour, blob, low_res); parts are indices into `shape.parts`."""
    parts = len(shape.parts)
    drawn = []
    if rng.random() < scene.roof_probability:
        stepped = bool(rng.random() < scene.stepped_share)
        roof = {"kind": "roof", "part": int(rng.integers(parts)), "style": "stepped" if stepped else "gable",
                "height": uniform(rng, scene.roof_height)}
        if stepped:  # the storey set back from each side of the top by 10-30% of it
            roof["inset"] = [0.1 + 0.2 * rng.random() for _ in range(4)]
        else:
            roof["along"] = "width" if rng.random() < 0.5 else "depth"  # the ridge's direction
        drawn.append(roof)
    if rng.random() < scene.chimney_probability:
        drawn.append({"kind": "chimney", "part": int(rng.integers(parts)), "height": uniform(rng, scene.chimney_height),
                      "width": uniform(rng, scene.chimney_width), "at": [0.1 + 0.8 * rng.random(), 0.1 + 0.8 * rng.random()]})
    if rng.random() < scene.parapet_probability:
        start = 0.7 * rng.random()
        drawn.append({"kind": "parapet", "part": int(rng.integers(parts)), "height": uniform(rng, scene.parapet_height),
                      "edge": ("front", "back", "left", "right")[int(rng.integers(4))],
                      "span": [start, start + 0.3 + (0.7 - start) * rng.random()]})
    if rng.random() < scene.neighbour_probability:
        drawn.append({"kind": "neighbour", "side": "left" if rng.random() < 0.5 else "right",
                      "width": uniform(rng, scene.neighbour_width), "height": uniform(rng, scene.neighbour_height),
                      "setback": 0.3 * (rng.random() - 0.5)})  # its front a little before or behind the box's
    if rng.random() < scene.blob_probability:
        drawn.append({"kind": "blob", "radius": uniform(rng, scene.blob_radius), "wobble": uniform(rng, scene.blob_wobble),
                      "wavelength": uniform(rng, scene.blob_wavelength)})
    if rng.random() < scene.low_res_probability:
        drawn.append({"kind": "low_res", "factor": uniform(rng, scene.low_res_factor)})
    return drawn


class PartFrame:
    """A part's own frame in the camera's: a point (u, h, t) is u of the way from its RIGHT side to its
    LEFT, h of its height up from its top (-1: its ground) and t from its BACK to its FRONT, in viewer
    terms (the sample's naming), so that LEFT is image-left and FRONT faces the camera."""

    def __init__(self, points3d: np.ndarray, part: tuple[int, ...]):
        corner = points3d[list(part)]  # Table 1 order: 4 * front + 2 * left + bottom
        self.origin = corner[0]  # BACK-RIGHT-TOP
        self.across = corner[2] - corner[0]
        self.up = corner[0] - corner[1]
        self.forward = corner[4] - corner[0]

    def points(self, u, h, t) -> np.ndarray:
        """(N, 3) camera-frame points of the (u, h, t) given as equal-length sequences."""
        u, h, t = (np.asarray(v, dtype=np.float64)[:, None] for v in (u, h, t))
        return self.origin + u * self.across + h * self.up + t * self.forward

    def block(self, u: tuple[float, float], h: tuple[float, float], t: tuple[float, float]) -> np.ndarray:
        """The 8 corners of the block spanning these ranges."""
        grid = np.array(np.meshgrid(u, h, t, indexing="ij")).reshape(3, -1)
        return self.points(*grid)

    def ratio(self) -> float:
        """The part's width over its depth: a square footprint's side in t for 1 in u."""
        return float(np.linalg.norm(self.across) / max(np.linalg.norm(self.forward), 1e-12))


def solid(deviation: dict, shape: Shape, points3d: np.ndarray) -> np.ndarray:
    """The camera-frame vertices of a solid deviation's convex solid."""
    kind = deviation["kind"]
    if kind == "neighbour":
        return neighbour(deviation, shape, points3d)
    frame = PartFrame(points3d, shape.parts[deviation["part"]])
    height = deviation["height"]
    if kind == "roof" and deviation["style"] == "gable":
        ridge = ([0.0, 1.0], [0.5, 0.5]) if deviation["along"] == "width" else ([0.5, 0.5], [0.0, 1.0])
        return np.concatenate([frame.block((0, 1), (0, 0), (0, 1)), frame.points(ridge[0], [height, height], ridge[1])])
    if kind == "roof":
        right, left, back, front = deviation["inset"]
        return frame.block((right, 1 - left), (0, height), (back, 1 - front))
    if kind == "chimney":
        (u, t), side = deviation["at"], deviation["width"]
        across = side * frame.ratio()  # a square footprint
        u, t = min(u, 1 - side), min(t, max(1 - across, 0.0))
        return frame.block((u, u + side), (0, height), (t, min(t + across, 1.0)))
    start, end = deviation["span"]
    edge = deviation["edge"]
    if edge in ("front", "back"):
        t = (1 - PARAPET_THICKNESS, 1.0) if edge == "front" else (0.0, PARAPET_THICKNESS)
        return frame.block((start, end), (0, height), t)
    u = (1 - PARAPET_THICKNESS, 1.0) if edge == "left" else (0.0, PARAPET_THICKNESS)
    return frame.block(u, (0, height), (start, end))


def neighbour(deviation: dict, shape: Shape, points3d: np.ndarray) -> np.ndarray:
    """A neighbour's block beside the outer side of the building's part on `side` (a twobox's left
    part is `shape.parts[1]`), standing on its ground, as deep as it and set back a little."""
    part = shape.parts[1 if deviation["side"] == "left" and len(shape.parts) == 2 else 0]
    frame = PartFrame(points3d, part)
    width, height, setback = deviation["width"], deviation["height"], deviation["setback"]
    u = (1.0, 1.0 + width) if deviation["side"] == "left" else (-width, 0.0)
    return frame.block(u, (-1.0, height - 1.0), (-setback, 1.0 - setback))


def solids(deviations: list[dict], shape: Shape, points3d: np.ndarray) -> list[np.ndarray]:
    """The camera-frame vertices of each solid deviation's solid, but for one that reaches toward or
    behind the camera (nearer than NEAREST_DEPTH of the building's nearest corner): left out, not
    drawn inside out."""
    nearest = float(points3d[:, 2].min())
    drawn = (solid(d, shape, points3d) for d in deviations if d["kind"] in SOLIDS)
    return [vertices for vertices in drawn if vertices[:, 2].min() >= NEAREST_DEPTH * nearest]


def structure_points(deviations: list[dict], shape: Shape, points3d: np.ndarray) -> np.ndarray:
    """(M, 3) every solid deviation's vertices in the camera frame: what the picture's framing must hold."""
    found = solids(deviations, shape, points3d)
    return np.concatenate(found) if found else np.empty((0, 3))


def with_structures(clean: np.ndarray, deviations: list[dict], shape: Shape, view: View) -> np.ndarray:
    """`clean` with the solid deviations' silhouettes added (a copy; the same mask without any)."""
    mask = clean.copy()
    intrinsics = Intrinsics.from_params(view.params)
    for vertices in solids(deviations, shape, view.points3d):
        fill_convex(mask, project(vertices, intrinsics))
    return mask


def degrade(mask: np.ndarray, deviations: list[dict], rng: np.random.Generator) -> np.ndarray:
    """`mask` as a segmentation network gives it: its corners rounded and its outline wobbling slowly
    (`blob`), and drawn small and upsampled (`low_res`); sizes in px at 256, scaled to the mask's."""
    size = mask.shape[0]
    for deviation in deviations:
        if deviation["kind"] == "blob":
            mask = rounded(mask, deviation["radius"] * size / 256)
            mask = roughen(mask, deviation["wobble"] * size / 256, deviation["wavelength"] * size / 256, rng)
        elif deviation["kind"] == "low_res":
            mask = low_resolution(mask, deviation["factor"])
    return mask


def rounded(mask: np.ndarray, radius: float) -> np.ndarray:
    """`mask` with its corners, convex and concave, rounded to about `radius` px (an opening, then a closing)."""
    r = int(round(radius))
    if r < 1:
        return mask
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    image = mask.view(np.uint8)
    opened = cv2.morphologyEx(image, cv2.MORPH_OPEN, disc)
    return cv2.morphologyEx(opened, cv2.MORPH_CLOSE, disc).view(bool)


def low_resolution(mask: np.ndarray, factor: float) -> np.ndarray:
    """`mask` drawn at size / `factor` px (each small pixel the share of the mask it covers) and brought
    back up by bilinear interpolation, cut at one half: a low-resolution segmentation's outline."""
    height, width = mask.shape
    small = (max(int(round(width / factor)), 2), max(int(round(height / factor)), 2))
    coarse = cv2.resize(mask.astype(np.float32), small, interpolation=cv2.INTER_AREA)
    return cv2.resize(coarse, (width, height), interpolation=cv2.INTER_LINEAR) > 0.5
