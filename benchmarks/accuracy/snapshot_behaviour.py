"""A snapshot of what the commands answer, to show that a refactoring changed no behaviour.

Run it before and after a change and compare the two folders (`diff -r BEFORE AFTER`):

    python benchmarks/accuracy/snapshot_behaviour.py --out /tmp/before
    ... change the code ...
    python benchmarks/accuracy/snapshot_behaviour.py --out /tmp/after --masks /tmp/before/masks
    diff -r -x masks -x spools /tmp/before /tmp/after && echo unchanged

It drives the commands a user runs, in subprocesses with one torch thread (the thread count
changes float sums): 52 generated 256 px masks (box and twobox, every scene) fitted by `infer`
with the cuboid fit and with `--networks-only`; `eval --cuboid` of both shipped models on a
fixed spool; and a 12-step phase 2 training run of a tiny model, whose weights (a digest per
tensor) and metrics (every field but the clock's) are kept. `--masks` reuses the masks and
spools of an earlier snapshot, so the two runs see the very same inputs.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import torch

ROOT = Path(__file__).resolve().parents[2]
SCENES = ("paper-clean", "paper", "street")
SHAPES = ("box", "twobox")
MASKS_PER_SET = (9, 9, 9, 9, 8, 8)  # 52 in all, in the order of (scene, shape) below
# Metrics that read the clock (how long a step took, how old its samples were), not the weights.
CLOCK_FIELDS = {"time", "step_time_s", "data_wait_fraction", "mean_age_s", "samples_per_s", "eta"}


def command(*args: str, out: Path | None = None) -> str:
    """Run a console command with one thread; its stdout (or raise with its stderr)."""
    env = os.environ | {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "CUBOIDTRAIN_THREADS": "1"}
    tool = Path(sys.executable).parent / args[0]  # the console scripts beside this interpreter
    done = subprocess.run([str(tool), *args[1:]], cwd=ROOT, env=env, capture_output=True, text=True)
    if done.returncode not in (0, 1) or (done.returncode == 1 and args[0] == "cuboidgen"):
        raise SystemExit(f"{' '.join(args)}: exit {done.returncode}\n{done.stderr[-3000:]}")
    if out is not None:
        out.write_text(done.stdout)
    return done.stdout


def make_inputs(folder: Path) -> None:
    """The masks (PNG, the generator's noisy masks) and two 256 px spools, from fixed seeds."""
    from shared.sample import decode
    from shared.spool import enumerate_spool, read_sample_bytes

    masks = folder / "masks"
    masks.mkdir(parents=True)
    sets = [(scene, shape) for scene in SCENES for shape in SHAPES]
    for (scene, shape), count in zip(sets, MASKS_PER_SET):
        spool = folder / "spools" / f"{scene}-{shape}"
        command("cuboidgen", "run", "--spool", str(spool), "--scene", scene, "--shape", shape, "--limit", "0",
                "--max-samples", str(count), "--seed", "11", "--workers", "1", "--no-dashboard")
        for i, name in enumerate(enumerate_spool(spool)[:count]):
            sample = decode(read_sample_bytes(spool, name))
            cv2.imwrite(str(masks / f"{scene}-{shape}-{i}.png"), sample.noisy.astype("uint8") * 255)
    command("cuboidgen", "run", "--spool", str(folder / "spools" / "train"), "--scene", "paper", "--shape", "box",
            "--size", "64", "--limit", "0", "--max-samples", "64", "--seed", "5", "--workers", "1", "--no-dashboard")


def tensor_digests(path: Path) -> dict:
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    return {name: hashlib.sha256(t.contiguous().numpy().tobytes()).hexdigest()[:16]
            for name, t in ckpt["model"].items()} | {"step": ckpt["step"]}


def snapshot(out: Path, inputs: Path) -> None:
    masks = sorted(str(p) for p in (inputs / "masks").glob("*.png"))
    assert len(masks) == sum(MASKS_PER_SET), len(masks)
    command("cuboidtrain", "infer", *masks, "--device", "cpu", "--json", str(out / "infer_cuboid.json"))
    command("cuboidtrain", "infer", *masks, "--device", "cpu", "--networks-only",
            "--json", str(out / "infer_networks.json"))
    for scene in ("paper", "street"):
        for shape in SHAPES:
            command("cuboidtrain", "eval", "--spool", str(inputs / "spools" / f"{scene}-{shape}"), "--shape", shape,
                    "--device", "cpu", "--cuboid", "--json", out=out / f"eval_{scene}_{shape}.json")
    run = out / "train"
    command("cuboidtrain", "run", "--phase", "2", "--spool", str(inputs / "spools" / "train"), "--shape", "box",
            "--size", "64", "--arch", "tiny", "--steps", "12", "--batch-size", "8", "--loader-workers", "0",
            "--seed", "3", "--threads", "1", "--device", "cpu", "--no-dashboard", "--out", str(run),
            "--checkpoint-every", "6", "--log-every", "1")
    metrics = [{k: v for k, v in json.loads(line).items() if k not in CLOCK_FIELDS}
               for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]
    (out / "train_metrics.json").write_text(json.dumps(metrics, indent=1, sort_keys=True))
    (out / "train_weights.json").write_text(json.dumps(tensor_digests(run / "last.pt"), indent=1, sort_keys=True))
    shutil.rmtree(run)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="A new folder for the snapshot.")
    parser.add_argument("--masks", type=Path, help="An earlier snapshot's folder: reuse its masks and spools.")
    args = parser.parse_args()
    args.out.mkdir(parents=True)
    inputs = args.masks.parent if args.masks else args.out
    if args.masks is None:
        make_inputs(args.out)
    snapshot(args.out, inputs)
    print(f"snapshot in {args.out}")


if __name__ == "__main__":
    main()
