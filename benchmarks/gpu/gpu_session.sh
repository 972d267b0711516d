#!/usr/bin/env bash
# One GPU lease's measurements and training, in one command of under 10 minutes (issue 29).
#
#   OUT=gpu-out COMMIT=$(git rev-parse --short HEAD) benchmarks/gpu/gpu_session.sh      (on the lent machine: python3 there holds torch)
#
# In order, each stage's output in $OUT as it ends, so that a lease cut short still returns
# what was done:
#   1. two validation spools and four generators (box and twobox, `paper` and `street`, 256 px,
#      a capped spool per shape) on the cores the trainers leave;
#   2. the framing on the GPU against the framing before issue 29 (bench_input --equivalence);
#   3. one training step by memory format (bench_memory_format: is channels-last faster?);
#   4. box and twobox side by side on the one GPU, --arch $ARCH at $SIZE px: phase 1 for
#      $P1_MIN minutes, phase 2 for $P2_MIN, a cosine over each chunk's minutes; the model
#      files (`cuboidtrain models pack`) to $OUT/box.pt and $OUT/twobox.pt;
#   5. the data wait of short probes, with the generators still running: compact 64 px and
#      the paper's arch at 256 px;
#   6. the input path's CPU cost with the GPU as the device (bench_input --device cuda).
# Try it on a CPU with tiny settings first:
#   OUT=/tmp/g ARCH=tiny SIZE=64 BATCH=16 P1_MIN=0.3 P2_MIN=0.3 PROBE_MIN=0.2 LIMIT=2000 VAL=64 \
#       PROBE_ARCHS="tiny:64:16" MF_ARGS="--archs tiny --sizes 64 --batch 8 --repeats 2" \
#       INPUT_ARGS="--sizes 64 --batch 16 --batches 2 --repeats 1" PY=.venv/bin/python benchmarks/gpu/gpu_session.sh
set -uo pipefail
OUT=${OUT:?OUT: the folder the results go to}
PY=${PY:-python3}
WORK=${WORK:-/tmp/gpu-work}
SIZE=${SIZE:-128} ARCH=${ARCH:-slim} BATCH=${BATCH:-256} SIGMA=${SIGMA:-3}
P1_MIN=${P1_MIN:-2.5} P2_MIN=${P2_MIN:-2.0} PROBE_MIN=${PROBE_MIN:-0.5}
P1_LR=${P1_LR:-1.5e-3} P2_LR=${P2_LR:-3e-4}
GEN_WORKERS=${GEN_WORKERS:-2} LOADER_WORKERS=${LOADER_WORKERS:-3}
LIMIT=${LIMIT:-20000} VAL=${VAL:-500}
PROBE_ARCHS=${PROBE_ARCHS:-"compact:64:256 paper:256:64"}  # arch:size:batch[:loader workers[:shape]] (box)
MF_ARGS=${MF_ARGS:-"--archs compact slim --sizes 64 128 --batch 256 --repeats 5"}
MF_PAPER_ARGS=${MF_PAPER_ARGS:-"--archs paper --sizes 256 --batch 64 --repeats 3"}
INPUT_ARGS=${INPUT_ARGS:-"--sizes 64 128 --batch 256 --batches 4 --repeats 3"}
SHAPES=${SHAPES:-"box twobox"}  # a capped spool and two generators (paper, street) each
STAGES=${STAGES:-"equivalence formats train probes input"}  # which of stages 2-6 run
mkdir -p "$OUT" "$WORK"
stage() { [[ " $STAGES " == *" $1 "* ]]; }
exec > >(tee -a "$OUT/log.txt") 2>&1
started=$(date +%s)
say() { echo "[$(( $(date +%s) - started )) s] $*"; }
# python itself, not a shell function, is what runs in the background: killing a function's
# subshell would leave its python behind
CUBOIDGEN=(-c 'import sys; from cuboidgen.cli import main; sys.argv[0] = "cuboidgen"; main()')
ct() { "$PY" -m cuboidtrain "$@"; }
export PYTHONUNBUFFERED=1

say "machine: $(nproc) cores; $(nvidia-smi -L 2>/dev/null || echo no GPU)"
"$PY" -c 'import torch, sys; print("python", sys.version.split()[0], "torch", torch.__version__, "cuda", torch.cuda.is_available())'

# Every background job (spool drawers, generators, trainers) is stopped on the way out, however
# the script ends: a TERM or Ctrl-C runs the EXIT trap once the foreground command returns.
children=()
stop_children() { kill -TERM "${children[@]}" 2>/dev/null; wait "${children[@]}" 2>/dev/null; }
trap stop_children EXIT
trap 'exit 143' TERM
trap 'exit 130' INT

# 1. the spools (each wait names its jobs: a bare one would wait for the tee above too)
drawing=()
for shape in $SHAPES; do
    seed=$([ $shape = box ] && echo 1 || echo 2)
    "$PY" "${CUBOIDGEN[@]}" run --spool "$WORK/val-paper-$shape" --shape $shape --size 256 --seed "${seed}5" --scene paper \
        --limit 0 --max-samples "$VAL" --workers 2 --no-dashboard > "$WORK/val-$shape.log" 2>&1 &
    drawing+=($!)
    children+=($!)
done
wait "${drawing[@]}"
generators=()
for shape in $SHAPES; do
    for scene in paper street; do
        seed=$([ $shape = box ] && echo 1 || echo 2)$([ $scene = paper ] && echo 1 || echo 2)
        "$PY" "${CUBOIDGEN[@]}" run --spool "$WORK/train-$shape" --shape $shape --size 256 --scene $scene --limit "$LIMIT" \
            --seed "$seed" --workers "$GEN_WORKERS" --no-dashboard > "$WORK/generator-$shape-$scene.log" 2>&1 &
        generators+=($!)
        children+=($!)
    done
done
say "validation spools drawn; ${#generators[@]} generators started"

# 2. framing on the device against the framing before issue 29
if stage equivalence; then
    "$PY" benchmarks/speed/bench_input.py --equivalence $(for shape in $SHAPES; do echo "$WORK/val-paper-$shape"; done) \
        --sizes 64 128 256 --device auto > "$OUT/equivalence.txt" 2>&1
    head -n 6 "$OUT/equivalence.txt"
    say "equivalence done"
fi

# 3. memory formats
if stage formats; then
    "$PY" benchmarks/gpu/bench_memory_format.py $MF_ARGS --json "$WORK/mf.json" | grep ' px '
    "$PY" benchmarks/gpu/bench_memory_format.py $MF_PAPER_ARGS --json "$WORK/mf-paper.json" | grep ' px '
    "$PY" -c 'import json, sys; rows = [r for f in sys.argv[2:] for r in json.load(open(f))["rows"]]
json.dump(rows, open(sys.argv[1], "w"), indent=1)' "$OUT/memory_format.json" "$WORK/mf.json" "$WORK/mf-paper.json"
    say "memory formats done"
fi

# 4. the shapes side by side
if stage train; then
    common=(--size "$SIZE" --arch "$ARCH" --sigma "$SIGMA" --reframe --batch-size "$BATCH" --loader-workers "$LOADER_WORKERS"
            --lr-schedule cosine --checkpoint-every 500 --no-dashboard --overwrite)
    pack() {  # pack SHAPE PHASE_DIR TARGET
        ct models pack --checkpoint "$2/last.pt" --out "$3" --scene paper --scene street \
            --recipe "benchmarks/gpu/gpu_session.sh at ${COMMIT:-?} (ARCH=$ARCH SIZE=$SIZE SIGMA=$SIGMA BATCH=$BATCH P1_MIN=$P1_MIN P2_MIN=$P2_MIN P1_LR=$P1_LR P2_LR=$P2_LR), $1 and the other shape side by side on one GPU, $(( 2 * $(wc -w <<< "$SHAPES") )) generators x $GEN_WORKERS workers beside them" \
            > "$2/pack.log" 2>&1 || { echo "pack $2 failed:"; tail -n 3 "$2/pack.log"; }
    }
    trainers=()
    for shape in $SHAPES; do
        "$PY" -m cuboidtrain run --phase 1 --spool "$WORK/train-$shape" --shape $shape "${common[@]}" --lr "$P1_LR" \
            --max-minutes "$P1_MIN" --out "$WORK/$shape/p1" > "$WORK/$shape-p1.log" 2>&1 &
        trainers+=($!)
        children+=($!)
    done
    wait "${trainers[@]}"
    for shape in $SHAPES; do tail -n 4 "$WORK/$shape-p1.log"; pack $shape "$WORK/$shape/p1" "$WORK/$shape/p1/model.pt"; done
    say "phase 1 done"
    trainers=()
    for shape in $SHAPES; do
        "$PY" -m cuboidtrain run --phase 2 --spool "$WORK/train-$shape" --shape $shape "${common[@]}" --lr "$P2_LR" \
            --max-minutes "$P2_MIN" --init "$WORK/$shape/p1/model.pt" --out "$WORK/$shape/p2" > "$WORK/$shape-p2.log" 2>&1 &
        trainers+=($!)
        children+=($!)
    done
    wait "${trainers[@]}"
    for shape in $SHAPES; do tail -n 4 "$WORK/$shape-p2.log"; pack $shape "$WORK/$shape/p2" "$OUT/$shape.pt"; done
    say "phase 2 done; model files: $(ls "$OUT"/*.pt 2>/dev/null | tr '\n' ' ')"
fi

# 5. data-wait probes, the generators still running
if stage probes; then
    for probe in $PROBE_ARCHS; do
        IFS=: read -r arch size batch workers shape <<< "$probe"  # workers: the trainer's default when left empty
        shape=${shape:-box} name=probe-$shape-$arch-$size${workers:+-w$workers}
        ct run --phase 1 --spool "$WORK/train-$shape" --shape $shape --size "$size" --arch "$arch" --reframe --batch-size "$batch" \
            ${workers:+--loader-workers "$workers"} --max-minutes "$PROBE_MIN" --no-dashboard --overwrite --out "$WORK/$name" \
            > "$WORK/$name.log" 2>&1
        tail -n 2 "$WORK/$name.log"
    done
    say "probes done"
fi
tar -czf "$OUT/runs.tgz" -C "$WORK" --exclude='*.pt' --exclude='train-*' --exclude='val-*' --exclude='tensorboard' . 2>/dev/null

# 6. the input path with the GPU as the device
if stage input; then
    timeout 60 "$PY" benchmarks/speed/bench_input.py --device auto $INPUT_ARGS --json "$OUT/input.json" | grep ' px '
fi
say "all done"
