#!/usr/bin/env bash
# The shape classifier (cuboidtrain/models/shipped/classifier.pt) trained on a lent GPU, in one command of
# under 10 minutes (docs/training.md, "The shape classifier"):
#
#   OUT=DIR COMMIT=$(git rev-parse --short HEAD) recipes/classifier.sh     (on the lent machine, repository root)
#   then here: CUBOID_MODELS=a folder of it and the shipped box.pt, twobox.pt, and
#   benchmarks/accuracy/bench_accuracy.py ... --selection-only; copy it into cuboidtrain/models/shipped/ only if better
#
# Draws a box and a twobox spool (SAMPLES samples of each of the paper, street and irregular scenes, split
# evenly over SIZES: a classifier drawn at 128 px alone called 256 px irregular masks twobox more often,
# box 92 -> 87% right; seeds clear of the shipped spools' and the benchmarks') with cuboidgen on every core, then
# trains on DEVICE until MINUTES after the start, the masks held on the GPU. What comes back: OUT/classifier.pt
# (its card says how it was made) and OUT/classifier.log. Carried wheels in $WHEELS (default .whl/) are installed first.
#
# On the CPU with tiny settings (tests/test_shape_call.py runs it so):
#   OUT=/tmp/c DEVICE=cpu SAMPLES=8 MINUTES=1 BATCH=8 SCENES=paper PY=.venv/bin/python recipes/classifier.sh
set -euo pipefail
OUT=${OUT:?OUT: the folder the lent machine sends back}
PY=${PY:-python3} DEVICE=${DEVICE:-cuda} MINUTES=${MINUTES:-9} SAMPLES=${SAMPLES:-40000} BATCH=${BATCH:-256}
WORK=${WORK:-/tmp/classifier-work} WHEELS=${WHEELS:-.whl} WORKERS=${WORKERS:-$(nproc)}
THREADS=${THREADS:-1}  # torch's CPU threads: on the GPU they only feed it
SCENES=${SCENES:-paper street irregular} SIZES=${SIZES:-128 256}
start=$(date +%s)
mkdir -p "$OUT"
if compgen -G "$WHEELS/*.whl" > /dev/null; then  # packages the lent machine lacks, carried as wheels
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$WHEELS"/*.whl
    export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
exec > >(tee -a "$OUT/classifier.log") 2>&1
rm -rf "$WORK"
seed=300
sizes=($SIZES)
for shape in box twobox; do
    for scene in $SCENES; do
        for size in "${sizes[@]}"; do
            seed=$((seed + 1))
            "$PY" -c "import sys; from cuboidgen.cli import main; sys.argv[0] = 'cuboidgen'; main()" run \
                --spool "$WORK/$shape" --shape "$shape" --size "$size" --seed "$seed" --scene "$scene" --limit 0 \
                --max-samples $(( (SAMPLES + ${#sizes[@]} - 1) / ${#sizes[@]} )) --workers "$WORKERS" --no-dashboard
        done
    done
done
# what is left of MINUTES, less a minute for reading and framing the masks and writing the file
left=$("$PY" -c "print(max(0.01, $MINUTES - ($(date +%s) - $start) / 60 - 1.0))")
echo "spools drawn in $(( $(date +%s) - start )) s; training for $left min on $DEVICE"
"$PY" -m cuboidtrain classifier train --box "$WORK/box" --twobox "$WORK/twobox" --minutes "$left" --device "$DEVICE" \
    --threads "$THREADS" --batch-size "$BATCH" $(printf -- '--scene %s ' $SCENES) --out "$OUT/classifier.pt" \
    --recipe "SAMPLES=$SAMPLES MINUTES=$MINUTES BATCH=$BATCH DEVICE=$DEVICE SCENES='$SCENES' SIZES='$SIZES' recipes/classifier.sh at ${COMMIT:-?}"
