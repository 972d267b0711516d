#!/usr/bin/env bash
# The shipped models (cuboidtrain/models/shipped/box.pt, twobox.pt): the compact arch at 64 px on a CPU.
#
#   recipes/shipped.sh box             train from scratch: phase 1, then phase 2
#   CONTINUE=1 recipes/shipped.sh box  continue from the shipped cuboidtrain/models/shipped/box.pt (phase 2 only;
#                                      RUN=runs/NAME keeps each continuation's checkpoints apart)
#   GREY=1 ...                         R reads a grey input (--grey-input: each model pixel's covered share)
#   IRREGULAR=N ...                    add N samples of the `irregular` scene (roof lines, chimneys, a neighbour's
#                                      corner, blobby edges; the truth stays the box's) to the training spool
#                                      (20,000 a shape at 1f9965d cost the networks 4-14%: not shipped, BENCHMARKS.md)
#   then: cuboidtrain models pack --checkpoint runs/shipped-box/p2/last.pt --out cuboidtrain/models/shipped/box.pt
#
# Data: a frozen 120,000-sample spool per shape class, half `paper`, half `street` scene,
# with occluders and contour noise, drawn at 128 px. The trainer frames every sample as
# `infer` frames a mask (--reframe: the largest visible component, 10% margin) at 64 px,
# so it trains on what it will be shown. Two generators writing one spool is the spool's
# ordinary multi-writer case. Budgets are wall-clock (--max-minutes) so that two shapes
# can train side by side on a 2-core machine, one thread each (THREADS=1, the default).
# Run again after an interruption, and each phase continues from its last checkpoint.
set -euo pipefail
SHAPE=${1:?usage: recipes/shipped.sh box|twobox}
BIN=${BIN:-.venv/bin}
SPOOLS=${SPOOLS:-spools}
RUN=${RUN:-runs/shipped-$SHAPE}
THREADS=${THREADS:-1}
PHASE1_STEPS=${PHASE1_STEPS:-1900} PHASE1_MINUTES=${PHASE1_MINUTES:-45}
PHASE2_STEPS=${PHASE2_STEPS:-2200} PHASE2_MINUTES=${PHASE2_MINUTES:-60} PHASE2_LR=${PHASE2_LR:-5e-4}
train=$SPOOLS/train-$SHAPE-128
val=$SPOOLS/val-paper-$SHAPE-256

resume() { if [ -f "$1/last.pt" ]; then echo --resume; else echo --overwrite; fi; }  # no checkpoint: start (over)
spool() {  # spool DIR SEED SCENE COUNT SIZE: add COUNT samples of SCENE, drawn once (a marker beside it says so)
    local drawn; drawn=$(dirname "$1")/.drawn-$(basename "$1")-$3
    if [ ! -f "$drawn" ]; then
        "$BIN/cuboidgen" run --spool "$1" --shape "$SHAPE" --size "$5" --seed "$2" --scene "$3" \
            --limit 0 --max-samples "$4" --workers 2 --no-dashboard
        touch "$drawn"
    fi
}
seed=$([ "$SHAPE" = box ] && echo 1 || echo 2)  # the shapes' spools differ in their seeds
SAMPLES=${SAMPLES:-60000}  # a scene's samples in the training spool
spool "$train" "${seed}1" paper "$SAMPLES" 128
spool "$train" "${seed}2" street "$SAMPLES" 128
if [ -n "${IRREGULAR:-}" ]; then spool "$train" "${seed}3" irregular "$IRREGULAR" 128; fi
spool "$val" "${seed}5" paper 500 256  # the seed of benchmarks/accuracy/bench_accuracy.py's noisy paper set

common=(--threads "$THREADS" --spool "$train" --shape "$SHAPE" --size 64 --arch compact --reframe --sigma 2 ${GREY:+--grey-input}
        --batch-size 32 --loader-workers 1 --lr-schedule cosine --checkpoint-every 200
        --val-spool "$val" --val-every 500 --val-samples 128 --no-dashboard)
if [ -z "${CONTINUE:-}" ]; then
    "$BIN/cuboidtrain" run --phase 1 "${common[@]}" --steps "$PHASE1_STEPS" --lr 1e-3 \
        --max-minutes "$PHASE1_MINUTES" --out "$RUN/p1" $(resume "$RUN/p1")
    init=$RUN/p1/last.pt
else
    init=cuboidtrain/models/shipped/$SHAPE.pt
fi
"$BIN/cuboidtrain" run --phase 2 "${common[@]}" --steps "$PHASE2_STEPS" --lr "$PHASE2_LR" \
    --max-minutes "$PHASE2_MINUTES" --init "$init" --out "$RUN/p2" $(resume "$RUN/p2")
