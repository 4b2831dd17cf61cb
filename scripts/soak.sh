#!/usr/bin/env bash
# The soak (issue 30): one `cmnav fly` process flies EPISODES episodes back to back against SITL
# vehicles (levels rotating, a vehicle fault every 4th episode), sampling its RSS, fds, threads,
# step p99 and the log directory after each; writes OUT/soak.csv, OUT/soak.png, OUT/verdict.json
# and exits 1 when a fitted trend fails (see bench/soak.py and docs/soak.md).
#   bash scripts/soak.sh                       # 200 episodes, models/default.onnx, into runs/soak
#   bash scripts/soak.sh 30 runs/soak-30       # a shorter one
#   MODEL=runs/models/goal-seeker.onnx bash scripts/soak.sh 30
# Extra options go to `python -m bench.soak` through SOAK_ARGS, e.g. SOAK_ARGS="--no-replay".
# It runs niced (it shares the machine); a 200-episode run takes hours.
set -euo pipefail
EPISODES=${1:-200}
OUT=${2:-runs/soak}
MODEL=${MODEL:-models/default.onnx}
PYTHON=${PYTHON:-.venv/bin/python}
if [ ! -f "$MODEL" ]; then
  echo "model $MODEL not found: build it with \`make models/default.onnx\` (or MODEL=runs/models/goal-seeker.onnx)" >&2
  exit 2
fi
# shellcheck disable=SC2086
exec nice -n 10 "$PYTHON" -m bench.soak --model "$MODEL" --episodes "$EPISODES" --out "$OUT" ${SOAK_ARGS:-}
