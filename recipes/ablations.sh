#!/usr/bin/env bash
# Table 3's ablations on the CPU recipe's spools, after `recipes/cpu.sh SHAPE` has run:
#
#   recipes/ablations.sh twobox   -> runs/cpu-twobox/finetune/last.pt and runs/cpu-twobox/e2e/last.pt
#
# finetune: the phase 1 model trained on with the final loss only (no intermediate
#           meaning), with phase 2's budget: "pre-trained with rep. meaning, trained without".
# e2e:      the same networks from random weights, final loss only, with phase 1 + 2's
#           budget together: "uninitialized, trained without rep. meaning".
# Run again after an interruption, and each continues from its last checkpoint.
set -euo pipefail
SHAPE=${1:?usage: recipes/ablations.sh box|twobox}
FINETUNE_STEPS=${FINETUNE_STEPS:-500}
E2E_STEPS=${E2E_STEPS:-2000}
source "$(dirname "$0")/common.sh"
if [ ! -f "$RUN/p1/last.pt" ]; then
    echo "no $RUN/p1/last.pt: run recipes/cpu.sh $SHAPE first" >&2
    exit 1
fi

"$BIN/cuboidtrain" run --phase finetune "${common[@]}" --steps "$FINETUNE_STEPS" --lr 2e-4 --max-minutes 10 \
    --init "$RUN/p1/last.pt" --out "$RUN/finetune" --no-dashboard $(resume "$RUN/finetune")
"$BIN/cuboidtrain" run --phase e2e "${common[@]}" --steps "$E2E_STEPS" --lr 1e-3 --max-minutes 34 \
    --out "$RUN/e2e" --no-dashboard $(resume "$RUN/e2e")
