"""Cityscapes extraction: cut occluder instances out of a Cityscapes `gtFine` tree into a folder
of PNG cutouts that `OccluderLibrary.from_dir` loads (the paper takes its occluders from
Cityscapes, 3.3.1 and Figure 15).
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from shared.errors import UsageError
from shared.files import atomic_path

# The package's one logger name, as before it was split into modules: log settings and tests name it.
log = logging.getLogger("cuboidgen.occluders")

# Official Cityscapes labelIds of the classes that typically stand in front of buildings.
DEFAULT_CLASSES: dict[str, int] = {
    "pole": 17, "traffic light": 19, "traffic sign": 20, "vegetation": 21, "person": 24, "rider": 25,
    "car": 26, "truck": 27, "bus": 28, "caravan": 29, "trailer": 30, "motorcycle": 32, "bicycle": 33,
}
_LABEL_SUFFIX, _INST_SUFFIX = "_gtFine_labelIds.png", "_gtFine_instanceIds.png"


def _resolve_classes(classes) -> dict[str, int]:
    names = list(DEFAULT_CLASSES) if classes is None else [classes] if isinstance(classes, str) else list(classes)
    for name in names:
        if name not in DEFAULT_CLASSES:
            raise UsageError(f"occluder class {name!r}: unknown (expected one of {', '.join(DEFAULT_CLASSES)})")
    return {n: DEFAULT_CLASSES[n] for n in names}


def _label_files(root: Path, splits) -> list[Path]:
    gt, layout = root / "gtFine", f"expected ROOT/gtFine/<split>/<city>/*{_LABEL_SUFFIX}"
    if not gt.is_dir():
        raise UsageError(f"cityscapes root {root}: no gtFine folder ({layout})")
    missing = [s for s in splits if not (gt / s).is_dir()]
    if missing:
        log.info("cityscapes: splits %s not under %s; skipped", missing, gt)
    files = [p for s in splits if s not in missing for p in sorted((gt / s).glob(f"*/*{_LABEL_SUFFIX}"))]
    if not files:
        raise UsageError(f"cityscapes root {root}: no labelIds files for splits {list(splits)} ({layout})")
    return files


def _pieces(label: np.ndarray, inst: np.ndarray | None, class_id: int):
    """(cropped mask, bbox) per object: instance ids where Cityscapes has them, else connected
    components, since stuff classes and crowd regions merge many objects under one id."""
    loose = label == class_id
    if inst is not None:
        ids = np.unique(inst[loose])
        for iid in ids[ids >= 1000]:
            ys, xs = np.nonzero(inst == iid)
            x, y, w, h = xs.min(), ys.min(), xs.max() + 1 - xs.min(), ys.max() + 1 - ys.min()
            yield inst[y:y + h, x:x + w] == iid, (x, y, w, h)
        loose = loose & (inst < 1000)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(loose.astype(np.uint8), connectivity=8)
    for i in range(1, n):
        x, y, w, h = (int(v) for v in stats[i, :4])
        yield lab[y:y + h, x:x + w] == i, (x, y, w, h)


def _read_frame(label_path: Path):
    label = cv2.imread(str(label_path), cv2.IMREAD_UNCHANGED)
    if label is None:
        log.warning("cityscapes: %s is not readable; skipped", label_path)
        return None, None
    label = label if label.ndim == 2 else label[..., 0]
    inst_path = label_path.with_name(label_path.name[:-len(_LABEL_SUFFIX)] + _INST_SUFFIX)
    inst = cv2.imread(str(inst_path), cv2.IMREAD_UNCHANGED) if inst_path.is_file() else None
    if inst is None or inst.shape[:2] != label.shape:
        log.info("cityscapes: no usable %s; using connected components", inst_path.name)
        inst = None
    return label, inst


def _extract_frame(label_path: Path, classes: dict[str, int], out: Path, min_pixels: int, counts):
    label, inst = _read_frame(label_path)
    if label is None:
        return
    rows, cols = label.shape
    stem = label_path.name[:-len(_LABEL_SUFFIX)]
    for name, class_id in classes.items():
        n = 0
        for crop, (x, y, w, h) in _pieces(label, inst, class_id):
            # pieces cut by the frame border are truncated and would make implausible cut-outs
            if crop.sum() < min_pixels or x == 0 or y == 0 or x + w == cols or y + h == rows:
                continue
            dest = out / f"{name.replace(' ', '-')}_{stem}_{n}.png"
            with atomic_path(dest) as tmp:  # a running generator may load this folder meanwhile
                if not cv2.imwrite(str(tmp), crop.astype(np.uint8) * 255):
                    raise OSError(f"cannot write occluder {dest}")
            n += 1
        counts[name] = counts.get(name, 0) + n


def extract_cityscapes(root, out, classes=None, min_pixels: int = 400,
                       splits=("train", "val", "test")) -> dict[str, int]:
    """Cut occluder instances out of a Cityscapes-format tree; returns counts per class.

    Files are named ``<class>_<city>_<seq>_<frame>_<n>.png`` (spaces in class names
    become '-') and hold single-channel 0/255 cut-outs ready for ``from_dir``."""
    chosen = _resolve_classes(classes)
    root, out = Path(root), Path(out)
    files = _label_files(root, splits)
    out.mkdir(parents=True, exist_ok=True)
    counts: dict[str, int] = {}
    for i, label_path in enumerate(files, 1):
        _extract_frame(label_path, chosen, out, min_pixels, counts)
        if i % 100 == 0 or i == len(files):
            log.info("cityscapes: %d/%d frames, %d occluders so far", i, len(files), sum(counts.values()))
    return {n: k for n, k in counts.items() if k}
