"""Configuration: the scene presets (what a sample is drawn from) and GenConfig (how the daemon runs).

A scene is every random range a sample is drawn from, with its units. Cameras and
streets differ, so scenes are named presets or a user's JSON/TOML file; the
resolved scene is stored in every sample's params and in the spool's metadata.
"""
from __future__ import annotations

import json
import os
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

from shared.errors import UsageError
from shared.shapes import SHAPES
from shared.spool import EVICT_EVERY

Range = tuple[float, float]


@dataclass(frozen=True)
class SceneConfig:
    """Ranges (uniform, inclusive) of everything drawn for one sample.

    Geometry is in object units; the box is the paper's canonical unit cube scaled
    per axis. The camera looks along +z with x right and y down (OpenCV).
    """

    name: str = "paper"
    # Box extents (the paper's Table 4 "Scale" rows): width (x), height (y), depth (z).
    width: Range = (0.5, 2.0)
    height: Range = (0.5, 2.0)
    depth: Range = (0.5, 2.0)
    # Rotation of the box about its centre, degrees: pitch (x), yaw (y), roll (z).
    pitch_deg: Range = (-10.0, 10.0)
    yaw_deg: Range = (-10.0, 10.0)
    roll_deg: Range = (-5.0, 5.0)
    # Centre offset from the optical axis; offset_y > 0 puts the box below the camera.
    offset_x: Range = (-2.0, 2.0)
    offset_y: Range = (0.0, 2.0)
    # If set, the box stands on the ground this far below the camera and offset_y is unused.
    eye_height: Range | None = None
    # Camera to box centre along the optical axis: the paper's "focal length" (projection
    # plane distance). After framing, only this ratio to the box size shapes perspective.
    distance: Range = (2.0, 10.0)
    # Camera tilted up (degrees): vertical edges converge upward, as in street photos.
    camera_pitch_deg: Range = (0.0, 0.0)
    flip_probability: float = 0.5  # mirror left-right; labels are re-derived in viewer terms
    # Framing: the silhouette's longer side fills the image less two margins (fraction of size).
    margin: Range = (0.06, 0.14)
    centre_jitter: float = 1.0  # how far off-centre the silhouette may sit, as a fraction of the margin
    # Two boxes: the middle wall's position (fraction of total width from the right) and
    # the lower part's height as a fraction of the taller one.
    split: Range = (0.3, 0.7)
    height_ratio: Range = (0.35, 0.85)
    # Occlusion: occluders per sample, their height (fraction of the silhouette's height),
    # rotation (degrees), and how often one stands on the building's ground line.
    occluders: tuple[int, int] = (0, 3)
    occluder_height: Range = (0.2, 0.8)
    occluder_rotation_deg: Range = (-15.0, 15.0)
    grounded_probability: float = 0.7
    # Contour noise: displacement of the silhouette's boundary, std in px at 256 px
    # (scaled with the image size), and the correlation length along the contour in px.
    contour_noise: Range = (0.0, 2.5)
    noise_wavelength: Range = (3.0, 12.0)

    def validate(self) -> "SceneConfig":
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, tuple) and (len(value) != 2 or value[0] > value[1]):
                raise UsageError(f"scene {self.name!r}: {f.name} = {value!r}, expected a range (min, max) with min <= max")
        for name in ("flip_probability", "grounded_probability", "centre_jitter"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise UsageError(f"scene {self.name!r}: {name} = {getattr(self, name)}, expected a value in [0, 1]")
        if min(self.width + self.height + self.depth) <= 0 or self.distance[0] <= 0:
            raise UsageError(f"scene {self.name!r}: extents and distance must be positive")
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

SCENES: dict[str, SceneConfig] = {s.name: s for s in (PAPER, PAPER_CLEAN, STREET)}


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
    base = SCENES.get(data.pop("base", "paper"))
    if base is None:
        raise UsageError(f"scene base must be one of {sorted(SCENES)}")
    known = {f.name for f in fields(SceneConfig)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise UsageError(f"scene: unknown field(s) {unknown}; expected some of {sorted(known)}")
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
    values.setdefault("name", default_name)
    return replace(base, **values).validate()


GEN_SHAPES = (*SHAPES, "mix")  # mix: each sample picks a shape class at random


@dataclass(frozen=True)
class GenConfig:
    """Everything `cuboidgen run` does; CLI options map one-to-one onto these fields."""

    spool: Path = Path("data_spool")
    limit: int = 10_000  # samples kept in the spool; 0 retains it (no eviction)
    max_samples: int | None = None  # stop after publishing this many (all workers together)
    workers: int = field(default_factory=lambda: os.cpu_count() or 1)
    size: int = 256  # px, square masks
    shape: str = "box"  # box | twobox | mix (each sample picks one at random)
    seed: int | None = None  # None: fresh entropy; a seed makes the whole run reproducible
    scene: SceneConfig = PAPER
    occluders: Path | None = None  # folder of RGBA/binary PNG cutouts; None: the built-in library
    dashboard: bool = True
    fsync: bool = False  # sync each sample before publishing (survives power loss; slower)
    evict_every: int = EVICT_EVERY  # publishes between spool listings (the bound on overshoot per writer)
    # samples a second, all workers together (each takes its share); None: as fast as they go.
    # A trainer that reads slower than this rate misses samples (README: the generator's throttle).
    max_rate: float | None = None

    def validate(self) -> "GenConfig":
        if self.limit < 0:
            raise UsageError(f"--limit {self.limit}: expected 0 (retain the spool) or a positive sample count")
        if self.max_samples is not None and self.max_samples < 1:
            raise UsageError(f"--max-samples {self.max_samples}: expected a positive count")
        if self.workers < 1:
            raise UsageError(f"--workers {self.workers}: expected at least 1")
        if not 16 <= self.size <= 4096:
            raise UsageError(f"--size {self.size}: expected 16 to 4096 px")
        if self.shape not in GEN_SHAPES:
            raise UsageError(f"--shape {self.shape!r}: expected one of {', '.join(GEN_SHAPES)}")
        if self.evict_every < 1:
            raise UsageError(f"--evict-every {self.evict_every}: expected at least 1")
        if self.max_rate is not None and not self.max_rate > 0:  # `not >` also refuses NaN
            raise UsageError(f"--max-rate {self.max_rate}: expected a positive number of samples a second")
        self.scene.validate()
        return self

    def to_dict(self) -> dict:
        d = asdict(self)
        d["spool"] = str(self.spool)
        d["occluders"] = str(self.occluders) if self.occluders else None
        return d
