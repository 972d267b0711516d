"""Configuration: the scene presets (what a sample is drawn from) and GenConfig (how the daemon runs).

A scene is every random range a sample is drawn from, with its units. Cameras and
streets differ, so scenes are named presets or a user's JSON/TOML file; the
resolved scene is stored in every sample's params and in the spool's metadata.
"""
from __future__ import annotations

import json
import os
import tomllib
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

from shared.checks import MAX_SEED, PER_CORE, check_numbers, max_processes, number, pair
from shared.errors import UsageError
from shared.shapes import SHAPES
from shared.spool import EVICT_EVERY

Range = tuple[float, float]
FAR = 1e6  # object units (metres in `street`): the largest magnitude of a scene's extents and positions
NEAR = 1e-3  # the smallest extent and distance: a box's ratios are divided by its extents
MAX_OCCLUDERS = 64  # per sample


@dataclass(frozen=True)
class SceneConfig:
    """Ranges (uniform, inclusive) of everything drawn for one sample.

    Geometry is in object units; the box is the paper's canonical unit cube scaled
    per axis. The camera looks along +z with x right and y down (OpenCV).
    """

    name: str = "paper"
    # Box extents (the paper's Table 4 "Scale" rows): width (x), height (y), depth (z).
    width: Range = pair((0.5, 2.0), lo=NEAR, hi=FAR)
    height: Range = pair((0.5, 2.0), lo=NEAR, hi=FAR)
    depth: Range = pair((0.5, 2.0), lo=NEAR, hi=FAR)
    # Rotation of the box about its centre, degrees: pitch (x), yaw (y), roll (z).
    pitch_deg: Range = pair((-10.0, 10.0), lo=-180, hi=180)
    yaw_deg: Range = pair((-10.0, 10.0), lo=-180, hi=180)
    roll_deg: Range = pair((-5.0, 5.0), lo=-180, hi=180)
    # Centre offset from the optical axis; offset_y > 0 puts the box below the camera.
    offset_x: Range = pair((-2.0, 2.0), lo=-FAR, hi=FAR)
    offset_y: Range = pair((0.0, 2.0), lo=-FAR, hi=FAR)
    # If set, the box stands on the ground this far below the camera and offset_y is unused.
    eye_height: Range | None = pair(None, lo=0, hi=FAR, optional=True)
    # Camera to box centre along the optical axis: the paper's "focal length" (projection
    # plane distance). After framing, only this ratio to the box size shapes perspective.
    distance: Range = pair((2.0, 10.0), lo=NEAR, hi=FAR)
    # Camera tilted up (degrees): vertical edges converge upward, as in street photos.
    camera_pitch_deg: Range = pair((0.0, 0.0), lo=-90, hi=90, lo_open=True, hi_open=True)
    flip_probability: float = number(0.5, lo=0, hi=1)  # mirror left-right; labels are re-derived in viewer terms
    # Framing: the silhouette's longer side fills the image less two margins (fraction of size).
    margin: Range = pair((0.06, 0.14), lo=0, hi=0.5, hi_open=True)
    centre_jitter: float = number(1.0, lo=0, hi=1)  # how far off-centre the silhouette may sit, as a fraction of the margin
    # Two boxes: the middle wall's position (fraction of total width from the right) and
    # the lower part's height as a fraction of the taller one.
    split: Range = pair((0.3, 0.7), lo=0.01, hi=0.99)  # each part at least 1% of the width
    height_ratio: Range = pair((0.35, 0.85), lo=0.01, hi=1)
    # Occlusion: occluders per sample, their height (fraction of the silhouette's height),
    # rotation (degrees), and how often one stands on the building's ground line.
    occluders: tuple[int, int] = pair((0, 3), lo=0, hi=MAX_OCCLUDERS, integer=True)
    occluder_height: Range = pair((0.2, 0.8), lo=0, lo_open=True, hi=4)
    occluder_rotation_deg: Range = pair((-15.0, 15.0), lo=-180, hi=180)
    grounded_probability: float = number(0.7, lo=0, hi=1)
    # Contour noise: displacement of the silhouette's boundary, std in px at 256 px
    # (scaled with the image size), and the correlation length along the contour in px.
    contour_noise: Range = pair((0.0, 2.5), lo=0, hi=64)
    noise_wavelength: Range = pair((3.0, 12.0), lo=0, lo_open=True, hi=4096)
    # Irregular buildings (the `irregular` scene; every probability 0 elsewhere): what real outlines show and a
    # box does not (cuboidgen/irregular.py). Each is drawn with its probability; sizes are fractions of the part
    # it stands on or beside (heights of its height, widths of its width), px are at 256 px.
    roof_probability: float = number(0.0, lo=0, hi=1)  # a roof on top of a part: pitched (gable) or stepped
    stepped_share: float = number(0.4, lo=0, hi=1)  # of those roofs, stepped (a set-back storey) rather than gable
    roof_height: Range = pair((0.08, 0.4), lo=0, hi=2)
    chimney_probability: float = number(0.0, lo=0, hi=1)  # a chimney standing on a part's top
    chimney_height: Range = pair((0.05, 0.2), lo=0, hi=2)
    chimney_width: Range = pair((0.03, 0.08), lo=0, lo_open=True, hi=0.5)
    parapet_probability: float = number(0.0, lo=0, hi=1)  # a low wall along part of one top edge
    parapet_height: Range = pair((0.02, 0.06), lo=0, hi=1)
    neighbour_probability: float = number(0.0, lo=0, hi=1)  # a neighbour's corner merged into one side
    neighbour_width: Range = pair((0.05, 0.25), lo=0, lo_open=True, hi=2)
    neighbour_height: Range = pair((0.3, 1.2), lo=0, lo_open=True, hi=4)
    blob_probability: float = number(0.0, lo=0, hi=1)  # blobby segmentation: rounded corners, a slow wobble
    blob_radius: Range = pair((2.0, 8.0), lo=0, hi=64)  # px: corners rounded to about this radius
    blob_wobble: Range = pair((0.5, 2.5), lo=0, hi=64)  # px: the wobble's std
    blob_wavelength: Range = pair((24.0, 64.0), lo=0, lo_open=True, hi=4096)  # px along the outline
    low_res_probability: float = number(0.0, lo=0, hi=1)  # drawn small and upsampled
    low_res_factor: Range = pair((2.0, 6.0), lo=1, hi=64)  # the image drawn at size / factor px

    def validate(self) -> "SceneConfig":
        """Every field checked for type, finiteness and range; the error names the field."""
        if not isinstance(self.name, str) or not self.name:
            raise UsageError(f"scene name {self.name!r}: expected a non-empty string")
        check_numbers(self, lambda field_name: f"scene {self.name!r}: {field_name}")
        return self


PAPER = SceneConfig()

# Street-level photos: a camera at eye height, tilted up at buildings in metres,
# seen at varying yaw and off-axis, so verticals converge and side faces show.
STREET = SceneConfig(
    name="street",
    width=(8.0, 40.0),
    height=(6.0, 35.0),
    depth=(8.0, 30.0),
    pitch_deg=(0.0, 0.0),
    yaw_deg=(-35.0, 35.0),
    roll_deg=(-2.0, 2.0),
    offset_x=(-15.0, 15.0),
    eye_height=(1.4, 1.8),
    distance=(25.0, 90.0),
    camera_pitch_deg=(3.0, 25.0),
)

# Table 3's validation: "no noise and occlusions were used".
PAPER_CLEAN = replace(PAPER, name="paper-clean", occluders=(0, 0), contour_noise=(0.0, 0.0))

# Irregular buildings (issue 37, Must have 6): `street`'s buildings and cameras, with what real outlines
# show beside the box: a roof line, a chimney or parapet, a neighbour's corner, blobby edges, low resolution.
IRREGULAR = replace(
    STREET,
    name="irregular",
    roof_probability=0.6,
    chimney_probability=0.35,
    parapet_probability=0.3,
    neighbour_probability=0.35,
    blob_probability=0.5,
    low_res_probability=0.35,
)

SCENES: dict[str, SceneConfig] = {s.name: s for s in (PAPER, PAPER_CLEAN, STREET, IRREGULAR)}


def load_scene(name_or_path: str) -> SceneConfig:
    """A preset by name, or a JSON/TOML file of fields overriding the `paper` preset
    (or the preset named by its `base` key)."""
    if name_or_path in SCENES:
        return SCENES[name_or_path]
    path = Path(name_or_path)
    if not path.is_file():
        raise UsageError(f"scene {name_or_path!r}: expected a preset ({', '.join(SCENES)}) or a .json/.toml file")
    try:
        text = path.read_text()
        data = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except (OSError, ValueError) as exc:
        raise UsageError(f"scene file {path}: cannot parse it ({exc})") from None
    return scene_from_dict(data, default_name=path.stem)


def scene_from_dict(data: dict, default_name: str = "custom") -> SceneConfig:
    if not isinstance(data, dict):
        raise UsageError(f"scene {default_name!r}: expected a table of fields (a JSON object), "
                         f"not {type(data).__name__} {data!r:.60}")
    data = dict(data)
    base = data.pop("base", "paper")
    if not isinstance(base, str) or base not in SCENES:
        raise UsageError(f"scene {default_name!r}: base must be one of {sorted(SCENES)}, not {base!r}")
    base = SCENES[base]
    known = {f.name for f in fields(SceneConfig)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise UsageError(f"scene {default_name!r}: unknown field(s) {unknown}; expected some of {sorted(known)}")
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
    values.setdefault("name", default_name)
    return replace(base, **values).validate()


GEN_SHAPES = (*SHAPES, "mix")  # mix: each sample picks a shape class at random


@dataclass(frozen=True)
class GenConfig:
    """Everything `cuboidgen run` does; CLI options map one-to-one onto these fields."""

    spool: Path = Path("data_spool")
    limit: int = number(10_000, lo=0, integer=True, unit="0 retains the spool")  # samples kept in the spool; 0 retains it (no eviction)
    max_samples: int | None = number(None, lo=1, integer=True, optional=True)  # stop after publishing this many (all workers together)
    workers: int = number(default_factory=lambda: os.cpu_count() or 1, lo=1, hi=max_processes(), integer=True,
                          unit=PER_CORE)
    size: int = number(256, lo=16, hi=4096, integer=True, unit="px")  # square masks
    shape: str = "box"  # box | twobox | mix (each sample picks one at random)
    seed: int | None = number(None, lo=0, hi=MAX_SEED, integer=True, optional=True)  # None: fresh entropy; a seed makes the whole run reproducible
    scene: SceneConfig = PAPER
    occluders: Path | None = None  # folder of RGBA/binary PNG cutouts; None: the built-in library
    dashboard: bool = True
    fsync: bool = False  # sync each sample before publishing (survives power loss; slower)
    evict_every: int = number(EVICT_EVERY, lo=1, integer=True)  # publishes between spool listings (the bound on overshoot per writer)
    # samples a second, all workers together (each takes its share); None: as fast as they go.
    # A trainer that reads slower than this rate misses samples (docs/generator.md: `--max-rate`).
    max_rate: float | None = number(None, lo=0, lo_open=True, optional=True, unit="samples a second")

    def validate(self) -> "GenConfig":
        check_numbers(self)  # every numeric field's declared range: finite, in range, the option named
        if not isinstance(self.shape, str) or self.shape not in GEN_SHAPES:
            raise UsageError(f"--shape {self.shape!r}: expected one of {', '.join(GEN_SHAPES)}")
        if not isinstance(self.scene, SceneConfig):
            raise UsageError(f"--scene {self.scene!r}: expected a SceneConfig (cuboidgen.config.load_scene)")
        self.scene.validate()
        return self

    def to_dict(self) -> dict:
        d = asdict(self)
        d["spool"] = str(self.spool)
        d["occluders"] = str(self.occluders) if self.occluders else None
        return d
