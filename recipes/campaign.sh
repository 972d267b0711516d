#!/usr/bin/env bash
# One lease of the GPU campaign (issue 40) in one command of under 10 minutes: docs/training.md,
# "A GPU lease: the campaign", gives the device tool's whole `run` line and what comes back.
#
#   OUT=DIR COMMIT=$(git rev-parse --short HEAD) recipes/campaign.sh      (on the lent machine, from the repository root)
#   .venv/bin/cuboidtrain campaign apply DIR                              (back here, with what it returned; then commit campaign/)
#
# In order (cuboidtrain/campaign/lease.py): a smoke check (CUDA visible, the project imports in a
# fresh interpreter, one step of the plan's model), failing in seconds in one line; a generator per
# shape and scene on the cores the trainers leave, fresh seeds each lease; each shape's standing run
# (campaign/plan.json, campaign/state.json) resumed side by side until MINUTES less the plan's
# eval_minutes; the new state (in parts of at most 15 MB), lease.json (the log row) and then
# eval.json (bench_accuracy's sets, the campaign's models and the shipped ones) into OUT, with this
# script's output as OUT/lease.log. Carried wheels in $WHEELS (default .whl/: watchdog, xxhash) are installed first.
#
# On the CPU with tiny settings (tests/test_campaign.py runs it so):
#   OUT=/tmp/lease DEVICE=cpu CAMPAIGN=/tmp/tiny-campaign MINUTES=4 PY=.venv/bin/python recipes/campaign.sh --lease-steps 2
set -uo pipefail
OUT=${OUT:?OUT: the folder the lent machine sends back}
PY=${PY:-python3}
MINUTES=${MINUTES:-9.5} DEVICE=${DEVICE:-cuda} CAMPAIGN=${CAMPAIGN:-campaign} WORK=${WORK:-/tmp/campaign-work}
WHEELS=${WHEELS:-.whl}  # the lent machine's Python's wheels (cp312): the tests here point it elsewhere
mkdir -p "$OUT"
if compgen -G "$WHEELS/*.whl" > /dev/null; then  # packages the lent machine lacks, carried as wheels
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$WHEELS"/*.whl || exit 1
    export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
exec > >(tee -a "$OUT/lease.log") 2>&1
tee_pid=$!
"$PY" -m cuboidtrain campaign lease --out "$OUT" --campaign "$CAMPAIGN" --minutes "$MINUTES" --device "$DEVICE" \
    --work "$WORK" ${COMMIT:+--commit "$COMMIT"} "$@"
status=$?
exec >&- 2>&-  # tee sees the end of its input and writes the log's last lines before OUT is sent back
wait "$tee_pid" 2>/dev/null
exit $status
