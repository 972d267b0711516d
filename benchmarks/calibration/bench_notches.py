"""Does the roof line's notch count (`silhouette.roof_notches`) tell merged buildings and blobs from
whole ones? Per kind of silhouette, the share with at least `trust.ROOF_NOTCHES` notches deeper than
each depth, and (with --rows) the share warned (any warning) and the share flagged `not-a-box` / `border-cut` before and after the count.

The masks are `bench_trust.py`'s: each seed set's generated noisy masks (every scene, 64, 128 and 256
px, box and twobox mixed), and from its 256 px ones the made silhouettes (cut by the border, two or
three merged, random blobs; the same draws as `bench_trust.made_rows`). Only the mask is read: no fit.

    .venv/bin/python benchmarks/calibration/bench_notches.py --sets measure fit \\
        [--rows runs/trust-measure-final.json runs/trust-fit.json]

--rows: `bench_trust.py --rows` files of the same sets; their records (camera free) are judged
again with the count added to their signs, so the flag columns are the shipped rule's.
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parent.parent / "accuracy")]
from bench_accuracy import SETS, spool_for, write_masks  # noqa: E402
from bench_trust import KINDS, SEED_SETS, SIZES, make, signs_now  # noqa: E402

from cuboidtrain.fit import trust  # noqa: E402
from cuboidtrain.geometry.silhouette import roof_notches  # noqa: E402

DEPTHS = (0.05, 0.08, 0.12)


def masks_of(group: str, spools: Path, samples: int, folder: Path) -> list[dict]:
    """Every mask of the seed set `group` (as bench_trust draws them): kind, scene, size, index, counts."""
    rows = []
    for (s, scene), (z, size) in itertools.product(enumerate(SETS), enumerate(SIZES)):
        files, _ = write_masks(spool_for(spools, "mix", scene, samples, size=size, seed=SEED_SETS[group] + 10 * s + z),
                               samples, folder)
        masks = [cv2.imread(f, cv2.IMREAD_GRAYSCALE) > 127 for f in files]
        made = {"whole": masks}
        if size == 256:
            rng = np.random.default_rng(7 + s)
            made |= {kind: [make(kind, masks, rng) for _ in masks] for kind in KINDS[1:]}
        rows += [{"set": group, "kind": kind, "scene": scene, "size": size, "index": k,
                  "notches": {depth: roof_notches(m, depth) for depth in DEPTHS}}
                 for kind, images in made.items() for k, m in enumerate(images)]
    return rows


def codes(stored: dict, notches: int | None) -> set[str]:
    """A stored record's warning codes under the code's rule, with the roof's notch count or without."""
    return {w.code for w in trust.judge(signs_now(stored) | {"roof_notches": float(notches or 0)}).warnings}


def table(rows: list[dict], stored: dict) -> None:
    keys = [("whole", scene) for scene in SETS] + [(kind, None) for kind in KINDS[1:]]
    heads = [f">= {trust.ROOF_NOTCHES} deeper than {d:.0%}" for d in DEPTHS] + (["warned, after", "flagged before", "after"] if stored else [])
    print(f"{'set':8s} {'kind':18s} {'masks':>5s} " + " ".join(f"{h:>22s}" for h in heads))
    for group in sorted({r["set"] for r in rows}, reverse=True):
        for kind, scene in keys:
            mine = [r for r in rows if r["set"] == group and r["kind"] == kind and scene in (None, r["scene"])]
            cells = [np.mean([r["notches"][d] >= trust.ROOF_NOTCHES for r in mine]) for d in DEPTHS]
            joined = [(stored[key], r) for r in mine if (key := (group, kind, r["scene"], r["size"], r["index"])) in stored]
            if joined:
                after = [codes(s, r["notches"][trust.ROOF_NOTCH_DEPTH]) for s, r in joined]
                cells += [np.mean([bool(c) for c in after]),
                          np.mean([bool(codes(s, None) & set(trust.FLAGS)) for s, _ in joined]),
                          np.mean([bool(c & set(trust.FLAGS)) for c in after])]
            elif stored:
                cells += [np.nan] * 3
            print(f"{group:8s} {kind + (f' {scene}' if scene else ''):18s} {len(mine):5d} "
                  + " ".join(f"{c:22.0%}" for c in cells))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sets", nargs="+", choices=tuple(SEED_SETS), default=tuple(SEED_SETS))
    parser.add_argument("--samples", type=int, default=100, help="masks a (seed set, scene, size) spool")
    parser.add_argument("--spools", type=Path, default=Path("bench-spools"))
    parser.add_argument("--rows", type=Path, nargs="*", default=(), help="bench_trust.py --rows files to judge again")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        rows = [r for group in args.sets for r in masks_of(group, args.spools, args.samples, Path(tmp))]
    stored = {(r["set"], r["kind"], r["scene"], r["size"], r["index"]): r for path in args.rows
              for r in json.loads(path.read_text()) if not r["failed"] and r["path"] == "cuboid"}
    table(rows, stored)


if __name__ == "__main__":
    main()
