# Sourced by recipes/cpu.sh and recipes/ablations.sh once SHAPE is set: the settings and the
# training options they share, kept in one place so Table 3's ablations train as the recipe does.
SIZE=${SIZE:-64}
BIN=${BIN:-.venv/bin}
SPOOLS=${SPOOLS:-spools}
RUN=${RUN:-runs/cpu-$SHAPE}
THREADS=${THREADS:-}  # e.g. THREADS=1 on a CPU shared with other busy processes

train=$SPOOLS/train-$SHAPE-$SIZE
clean=$SPOOLS/val-clean-$SHAPE-$SIZE
noisy=$SPOOLS/val-noisy-$SHAPE-$SIZE

# Run a recipe again after an interruption, and each run continues from its last checkpoint.
resume() { if [ -f "$1/last.pt" ]; then echo --resume; else echo --overwrite; fi; }  # no checkpoint: start (over)
threads=(); if [ -n "$THREADS" ]; then threads=(--threads "$THREADS"); fi
# The paper's networks on the generator's own framing: Table 3 as it was measured (recipes/shipped.sh
# trains the shipped, compact models instead).
common=("${threads[@]}" --arch paper --no-reframe --spool "$train" --shape "$SHAPE" --size "$SIZE" --batch-size 16 --loader-workers 1
        --lr-schedule cosine --checkpoint-every 200 --val-spool "$clean" --val-every 400 --val-samples 128)
