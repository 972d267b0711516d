#!/usr/bin/env bash
# The GPU recipe: the paper's 256x256 setup, one shape class, on one CUDA GPU.
#
#   recipes/gpu.sh box        (or twobox)       -> runs/gpu-box/p2/last.pt and its evaluation
#
# The generator runs beside the trainer on the CPU cores and keeps a rotating
# 10,000-sample spool (paper 3.3.2); the trainer enumerates it every epoch.
# Not yet run by us: no GPU was lent while it was written (see BENCHMARKS.md).
set -euo pipefail
SHAPE=${1:?usage: recipes/gpu.sh box|twobox}
BIN=${BIN:-.venv/bin}
SPOOLS=${SPOOLS:-spools}
RUN=${RUN:-runs/gpu-$SHAPE}
GEN_WORKERS=${GEN_WORKERS:-$(( $(nproc) - 4 ))}
train=$SPOOLS/train-$SHAPE-256
clean=$SPOOLS/val-clean-$SHAPE-256

"$BIN/cuboidgen" run --spool "$clean" --shape "$SHAPE" --size 256 --seed 2 --scene paper-clean \
    --limit 0 --max-samples 1000 --no-dashboard
mkdir -p "$RUN"
"$BIN/cuboidgen" run --spool "$train" --shape "$SHAPE" --size 256 --limit 10000 --workers "$GEN_WORKERS" \
    --no-dashboard > "$RUN-generator.log" 2>&1 &
generator=$!
trap 'kill -TERM $generator 2>/dev/null; wait $generator' EXIT

common=(--spool "$train" --shape "$SHAPE" --size 256 --batch-size 64 --loader-workers 4 --lr-schedule cosine
        --checkpoint-every 1000 --val-spool "$clean" --val-every 2000 --val-samples 500)
"$BIN/cuboidtrain" run --phase 1 "${common[@]}" --steps 40000 --lr 1e-3 --out "$RUN/p1"
"$BIN/cuboidtrain" run --phase 2 "${common[@]}" --steps 15000 --lr 2e-4 --init "$RUN/p1/last.pt" --out "$RUN/p2"
"$BIN/cuboidtrain" eval --checkpoint "$RUN/p2/last.pt" --spool "$clean" --json > "$RUN/eval-p2-clean.json"
"$BIN/cuboidtrain" eval --checkpoint "$RUN/p2/last.pt" --spool "$clean"
