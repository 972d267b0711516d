#!/usr/bin/env bash
# The GPU recipe: one CUDA GPU, the generator beside it on the same machine's CPU cores (issue 29).
#
#   recipes/gpu.sh box        (or twobox)   -> runs/gpu-box/p2/model.pt, a model file, and its evaluation
#
# What was measured (BENCHMARKS.md, "The input path" and "On a GPU"): the trainer frames each
# sample on the GPU (--reframe), so a loader worker only reads, decodes and finds a sample's
# framing, about 8,000 samples/s of one core (6,500 on the H100 machine's, beside generators);
# two generators (`paper` and `street` scenes, a 256 px spool of 20,000 samples each) get the
# cores the trainer leaves. On one H100 with 16 cores the data wait was 3.7-6.5% of step time
# (compact 64 and 128 px, the paper's arch at 256 px, about 2,000 samples/s; 55-68% before the
# framing moved to the GPU), and the model channels-last (on CUDA always) made a step 2.6-3.3x
# faster. When the GPU outruns the generators the trainer re-reads the spool (its reuse, paper
# 3.3.2): no faster generator is needed, and the dashboard says so.
#
# Each phase trains in chunks of at most CHUNK_MINUTES (10) that resume (--resume), so a lease
# that ends, a preemption or a crash loses one chunk at most; after each chunk its model file
# (`cuboidtrain models pack`: float16 weights, no optimizer state, at most MAX_MODEL_MB) is written
# beside the checkpoint. Run it again after an interruption and it continues where it stopped.
set -euo pipefail
SHAPE=${1:?usage: recipes/gpu.sh box|twobox}
BIN=${BIN:-.venv/bin}
SPOOLS=${SPOOLS:-spools}
RUN=${RUN:-runs/gpu-$SHAPE}
SIZE=${SIZE:-128} ARCH=${ARCH:-compact} BATCH=${BATCH:-256}  # compact: a 4 MB model file at any size
CHUNK_MINUTES=${CHUNK_MINUTES:-10} MAX_MODEL_MB=${MAX_MODEL_MB:-15}
PHASE1_STEPS=${PHASE1_STEPS:-6000} PHASE2_STEPS=${PHASE2_STEPS:-3000}
CORES=$(nproc)
LOADER_WORKERS=${LOADER_WORKERS:-$(( CORES / 4 > 2 ? CORES / 4 : 2 ))}  # TrainConfig.workers_on's CUDA default
left=$(( CORES - 1 - LOADER_WORKERS ))  # what the trainer's main process and its workers leave
GEN_WORKERS=${GEN_WORKERS:-$(( left / 2 > 1 ? left / 2 : 1 ))}  # each of the two generators
train=$SPOOLS/train-$SHAPE-256
val=$SPOOLS/val-paper-$SHAPE-256
seed=$([ "$SHAPE" = box ] && echo 1 || echo 2)

resume() { if [ -f "$1/last.pt" ]; then echo --resume; else echo --overwrite; fi; }  # no checkpoint: start (over)
reached() {  # the step OUT/status.json says the run reached (0 before its first)
    "$BIN/python" -c 'import json, sys
try: print(int(json.load(open(sys.argv[1])).get("step") or 0))
except (OSError, ValueError): print(0)' "$1/status.json"
}
pack() {  # the model file of OUT's checkpoint, refused above MAX_MODEL_MB
    "$BIN/cuboidtrain" models pack --checkpoint "$1/last.pt" --out "$1/model.pt" --scene paper --scene street \
        --recipe "recipes/gpu.sh $SHAPE (SIZE=$SIZE ARCH=$ARCH BATCH=$BATCH)"
    if [ "$(stat -c %s "$1/model.pt")" -gt $(( MAX_MODEL_MB * 1024 * 1024 )) ]; then
        echo "$1/model.pt: over $MAX_MODEL_MB MB (ARCH=$ARCH); pick a smaller arch" >&2
        exit 1
    fi
}
phase() {  # phase NAME STEPS OUT [OPTION...]: chunk after chunk until OUT reaches STEPS, packed after each
    local name=$1 steps=$2 out=$3
    shift 3
    while [ "$(reached "$out")" -lt "$steps" ]; do
        "$BIN/cuboidtrain" run --phase "$name" "${common[@]}" --steps "$steps" --max-minutes "$CHUNK_MINUTES" \
            --out "$out" $(resume "$out") "$@"
        pack "$out"
    done
}

if [ ! -f "$(dirname "$val")/.drawn-$(basename "$val")" ]; then  # bench_accuracy.py's noisy paper set
    "$BIN/cuboidgen" run --spool "$val" --shape "$SHAPE" --size 256 --seed "${seed}5" --scene paper \
        --limit 0 --max-samples 500 --no-dashboard
    touch "$(dirname "$val")/.drawn-$(basename "$val")"
fi
mkdir -p "$RUN"
generators=()
for scene in paper street; do
    "$BIN/cuboidgen" run --spool "$train" --shape "$SHAPE" --size 256 --scene "$scene" --limit 20000 \
        --seed "$seed$([ "$scene" = paper ] && echo 1 || echo 2)" --workers "$GEN_WORKERS" \
        --no-dashboard > "$RUN/generator-$scene.log" 2>&1 &
    generators+=($!)
done
trap 'kill -TERM "${generators[@]}" 2>/dev/null; wait "${generators[@]}"' EXIT

common=(--spool "$train" --shape "$SHAPE" --size "$SIZE" --arch "$ARCH" --reframe --batch-size "$BATCH"
        --loader-workers "$LOADER_WORKERS" --lr-schedule cosine --checkpoint-every 500
        --val-spool "$val" --val-every 1000 --val-samples 500 --no-dashboard)
phase 1 "$PHASE1_STEPS" "$RUN/p1" --lr 1e-3
phase 2 "$PHASE2_STEPS" "$RUN/p2" --lr 2e-4 --init "$RUN/p1/model.pt"
"$BIN/cuboidtrain" eval --checkpoint "$RUN/p2/model.pt" --spool "$val" --json > "$RUN/eval-p2.json"
"$BIN/cuboidtrain" eval --checkpoint "$RUN/p2/model.pt" --spool "$val"
