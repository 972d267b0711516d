"""Occluder silhouettes for the synthetic-sample generator (paper 3.3.1, Figure 15).

The paper imitates partial occlusion by subtracting cutouts of urban objects (trees,
cars, pedestrians, poles, signs; taken from Cityscapes) from clean building
silhouettes. Three roles, one module each:

* `urban_elements`: such objects drawn procedurally, so no dataset is needed;
* `library`: `OccluderLibrary`, the set occluders are chosen from: `builtin()` (drawn),
  `from_dir()` (RGBA or binary PNG cutouts) or `load()` (either);
* `cityscapes`: `extract_cityscapes()` makes such a folder from a Cityscapes `gtFine` tree.

Every mask is a tight-cropped, upright 0/1 uint8 array whose bottom row is the ground
contact, so the generator can scale, flip and place it freely.
"""
from cuboidgen.occluders.cityscapes import DEFAULT_CLASSES, extract_cityscapes
from cuboidgen.occluders.library import OccluderLibrary
from cuboidgen.occluders.urban_elements import KINDS

__all__ = ["DEFAULT_CLASSES", "KINDS", "OccluderLibrary", "extract_cityscapes"]
