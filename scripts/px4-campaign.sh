#!/usr/bin/env bash
# Fly a model on real PX4 v1.16 SITL (SIH quadrotor) through the camera-world follower, a fresh
# PX4 per flight, and print the outcome table (scripts/campaign-table.py):
#   bash scripts/px4-campaign.sh PX4_BUILD_DIR MODEL.onnx "0 3 6" 20 [OUT_DIR]
# PX4_BUILD_DIR is PX4-Autopilot/build/px4_sitl_default (docs/px4-sitl.md says how to build it).
# Each flight: PX4 started in an empty working folder, `cmnav sitl --autopilot udp://127.0.0.1:14550`
# (the follower waits until PX4 is ready), PX4 stopped by its PID.  Kept in OUT_DIR (default
# runs/px4-campaign/<model name>): summaries.jsonl, runs/ (per flight: summary, MCAP log, plot,
# report), px4-logs/ (PX4's console per flight).  SEED_START (default 7001), TIMEOUT_S (20),
# INJECT (e.g. "camera-stall@3": passed to every flight as --inject), DEGRADE (the camera's depth,
# `cmnav sitl --degrade`: none, projector-off, stereo or stereo-projector-off; default none),
# APPROACH_CAP (`cmnav sitl --approach-cap`: on or off; default on),
# CMNAV / PYTHON as in scripts/sitl-campaign.sh.  PX4 never runs outside this script's flights; nothing binds
# anything but 127.0.0.1 on our side.
set -euo pipefail
build=$(realpath "$1"); MODEL=$2; LEVELS=${3:-"0"}; SEEDS=${4:-20}
OUT=${5:-runs/px4-campaign/$(basename "$MODEL" .onnx)}
mkdir -p "$OUT" && OUT=$(realpath "$OUT")  # PX4 runs in its own working folder: every path absolute
SEED_START=${SEED_START:-7001}
TIMEOUT_S=${TIMEOUT_S:-20}
INJECT=${INJECT:-}
DEGRADE=${DEGRADE:-none}
APPROACH_CAP=${APPROACH_CAP:-on}
CMNAV=${CMNAV:-.venv/bin/cmnav}
PYTHON=${PYTHON:-.venv/bin/python}
[ -x "$build/bin/px4" ] || { echo "error: no PX4 binary at $build/bin/px4: build PX4 as docs/px4-sitl.md says" >&2; exit 2; }
mkdir -p "$OUT/px4-logs" "$OUT/runs"
: > "$OUT/summaries.jsonl"
px4_pid=
rootfs=
stop_px4() {
  if [ -n "$px4_pid" ]; then kill "$px4_pid" 2>/dev/null || true; wait "$px4_pid" 2>/dev/null || true; px4_pid=; fi
  if [ -n "$rootfs" ]; then rm -rf "$rootfs"; rootfs=; fi
}
trap stop_px4 EXIT
inject_args=()
for fault in $INJECT; do inject_args+=(--inject "$fault"); done
for level in $LEVELS; do
  for seed in $(seq "$SEED_START" $((SEED_START + SEEDS - 1))); do
    rootfs=$(mktemp -d /tmp/px4-campaign-XXXXXX)
    (cd "$rootfs" && PX4_SYS_AUTOSTART=10040 PX4_SIM_MODEL=sihsim_quadx exec "$build/bin/px4" -d "$build/etc" \
        >"$OUT/px4-logs/level${level}-seed${seed}.log" 2>&1 </dev/null) &
    px4_pid=$!
    summary=$("$CMNAV" sitl --autopilot udp://127.0.0.1:14550 --model "$MODEL" --level "$level" --seed "$seed" \
        --timeout "$TIMEOUT_S" --degrade "$DEGRADE" --approach-cap "$APPROACH_CAP" --out "$OUT/runs" --json "${inject_args[@]}" 2>>"$OUT/sitl.log" | tail -n 1) || true
    stop_px4
    if [ -z "$summary" ]; then
      # No episode (e.g. PX4's take-off never reached its height): not in the table; sitl.log says why.
      echo "level $level seed $seed: no summary, not flown (see $OUT/sitl.log)"
      continue
    fi
    echo "$summary" >> "$OUT/summaries.jsonl"
    echo "level $level seed $seed: $(echo "$summary" | "$PYTHON" -c 'import json,sys; r=json.loads(sys.stdin.read() or "{}"); print(r.get("outcome"), r.get("abort_reason"), r.get("time_s"))' 2>/dev/null)"
  done
done
"$PYTHON" "$(dirname "$0")/campaign-table.py" "$OUT/summaries.jsonl"
