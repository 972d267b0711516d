#!/usr/bin/env bash
# The CPU recipe: a usable 64 px model of one shape class on a 2-core machine in under an hour.
#
#   recipes/cpu.sh box        (or twobox)       -> runs/cpu-box/p2/last.pt and its evaluation
#
# On two cores a generator running beside the trainer would take half the machine,
# so this recipe first draws a frozen 20,000-sample spool (--limit 0, about 10 s at
# 64 px) and trains on it; with a GPU, run `cuboidgen run` alongside instead (GPU.md).
# Budgets: phase 1 at most 24 minutes, phase 2 at most 10, evaluation about 2.
set -euo pipefail
SHAPE=${1:?usage: recipes/cpu.sh box|twobox}
PHASE1_STEPS=${PHASE1_STEPS:-1500}
PHASE2_STEPS=${PHASE2_STEPS:-500}
source "$(dirname "$0")/common.sh"

spool() {  # spool DIR SEED SCENE COUNT: a frozen spool, drawn once
    if [ "$(find "$1" -name '*.cub' 2>/dev/null | wc -l)" -lt "$4" ]; then
        rm -rf "$1"
        "$BIN/cuboidgen" run --spool "$1" --shape "$SHAPE" --size "$SIZE" --seed "$2" --scene "$3" \
            --limit 0 --max-samples "$4" --workers 2 --no-dashboard
    fi
}
spool "$train" 1 paper 20000
spool "$clean" 2 paper-clean 500
spool "$noisy" 3 paper 500

"$BIN/cuboidtrain" run --phase 1 "${common[@]}" --steps "$PHASE1_STEPS" --lr 1e-3 --max-minutes 24 \
    --out "$RUN/p1" --no-dashboard $(resume "$RUN/p1")
"$BIN/cuboidtrain" run --phase 2 "${common[@]}" --steps "$PHASE2_STEPS" --lr 2e-4 --max-minutes 10 \
    --init "$RUN/p1/last.pt" --out "$RUN/p2" --no-dashboard $(resume "$RUN/p2")

for model in p1 p2; do
    for val in clean noisy; do
        spool_dir=$SPOOLS/val-$val-$SHAPE-$SIZE
        "$BIN/cuboidtrain" eval --checkpoint "$RUN/$model/last.pt" --spool "$spool_dir" --json \
            > "$RUN/eval-$model-$val.json"
        echo "$SHAPE $model on $val: $(python3 -c "import json,sys; r=json.load(open(sys.argv[1])); print(f\"mean {r['mean_px_error']:.2f} px, median {r['median_px_error']:.2f} px, random init {r['random_init_mean_px_error']:.2f} px\")" "$RUN/eval-$model-$val.json")"
    done
done
