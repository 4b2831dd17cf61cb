#!/usr/bin/env bash
# Fly one model in SITL over many seeds and levels and print the outcome table:
#   bash scripts/sitl-campaign.sh MODEL.onnx "0 3" 20 [OUT_DIR]
# (levels, seeds per level).  Each flight is `cmnav sitl --json`; the summaries go to
# OUT_DIR/summaries.jsonl (default runs/sitl-campaign/<model name>).  Besides outcomes it counts
# the watchdog's trips: those in flights that did not crash (false alarms: nothing is injected
# here), and the crashes the runtime caught within 1.5 s (tracking or vehicle_fault).
#
# Variants side by side (issue 15): VARIANTS="fp32 int8" flies each export of MODEL (fp32 = MODEL,
# int8 = MODEL's int8 file next to it, see `cmnav export --variants`) on the same levels and seeds,
# into OUT_DIR/<variant>/, and prints per level each variant's success rate with its Wilson 95 %
# interval and whether it lies within the first variant's.  With REPLAY_VARIANT=int8 every flight
# of the first variant is also replayed (`cmnav replay LOG --model <int8 file>`): the would-be
# action differences of that variant on the first one's recorded frames and telemetry.
#   VARIANTS="fp32 int8" REPLAY_VARIANT=int8 bash scripts/sitl-campaign.sh MODEL.onnx "0 3" 20
# CMNAV / PYTHON pick the programs (default .venv/bin/cmnav, .venv/bin/python); TIMEOUT_S the
# offboard time limit per flight; SEED_START the first seed (default 0); DEGRADE the SITL camera's
# depth (`cmnav sitl --degrade`: none, projector-off, stereo or stereo-projector-off; default none).
set -euo pipefail
MODEL=$1
LEVELS=${2:-"0"}
SEEDS=${3:-20}
SEED_START=${SEED_START:-0}  # first seed: SEED_START=10 with 10 seeds flies seeds 10-19 (to extend a campaign)
OUT=${4:-runs/sitl-campaign/$(basename "$MODEL" .onnx)}
CMNAV=${CMNAV:-.venv/bin/cmnav}
PYTHON=${PYTHON:-.venv/bin/python}
TIMEOUT_S=${TIMEOUT_S:-20}  # offboard time limit per flight (training episodes last 10 s)
VARIANTS=${VARIANTS:-}
REPLAY_VARIANT=${REPLAY_VARIANT:-}
DEGRADE=${DEGRADE:-none}

variant_file() {  # the file of variant $2 of model $1 (runtime.config.variant_path)
  "$PYTHON" -c 'import sys; from runtime.config import variant_path; print(variant_path(sys.argv[1], sys.argv[2]))' "$1" "$2"
}

fly() {  # fly model $1 on every level and seed into $2
  mkdir -p "$2"
  : > "$2/summaries.jsonl"
  for level in $LEVELS; do
    for seed in $(seq "$SEED_START" $((SEED_START + SEEDS - 1))); do
      "$CMNAV" sitl --model "$1" --level "$level" --seed "$seed" --timeout "$TIMEOUT_S" --degrade "$DEGRADE" --out "$2/runs" --json 2>>"$2/sitl.log" \
        | tail -n 1 >> "$2/summaries.jsonl" || true
    done
  done
}

if [ -z "$VARIANTS" ]; then
  fly "$MODEL" "$OUT"
  "$PYTHON" "$(dirname "$0")/campaign-table.py" "$OUT/summaries.jsonl"
  exit 0
fi

for variant in $VARIANTS; do
  file=$(variant_file "$MODEL" "$variant")
  [ -f "$file" ] || { echo "no $variant export of $MODEL ($file): cmnav export ... --variants $variant" >&2; exit 2; }
  fly "$file" "$OUT/$variant"
done
if [ -n "$REPLAY_VARIANT" ]; then
  first=${VARIANTS%% *}
  replay_model=$(variant_file "$MODEL" "$REPLAY_VARIANT")
  : > "$OUT/replay-$REPLAY_VARIANT.jsonl"
  "$PYTHON" -c 'import json, sys; [print(json.loads(l)["log"]) for l in open(sys.argv[1]) if l.strip().startswith("{") and json.loads(l).get("log")]' \
    "$OUT/$first/summaries.jsonl" | while read -r log; do
    "$CMNAV" replay "$log" --model "$replay_model" --json 2>>"$OUT/replay.log" | tail -n 1 >> "$OUT/replay-$REPLAY_VARIANT.jsonl" || true
  done
fi
"$PYTHON" - "$OUT" $VARIANTS <<'PY'
import collections, json, sys
from pathlib import Path

from training.stats import wilson_interval

out, variants = Path(sys.argv[1]), sys.argv[2:]


rates = {}
for v in variants:
    rows = [json.loads(line) for line in open(out / v / "summaries.jsonl") if line.strip().startswith("{")]
    by_level = collections.defaultdict(list)
    for r in rows:
        by_level[r["level"]].append(r)
    for level, rs in by_level.items():
        k = sum(r["outcome"] == "success" for r in rs)
        p99 = sorted(r["step_ms"]["p99"] for r in rs if r.get("step_ms") and r["step_ms"].get("p99") is not None)
        rates[level, v] = (k, len(rs), wilson_interval(k, len(rs)), p99[len(p99) // 2] if p99 else float("nan"))
base = variants[0]
print(f"| level | variant | flights | success % | 95 % interval | within {base}'s interval | step p99 ms (median) |")
print("|---|---|---|---|---|---|---|")
for level in sorted({lv for lv, _ in rates}):
    lo, hi = rates.get((level, base), (0, 0, (float("nan"), float("nan")), 0))[2]
    for v in variants:
        if (level, v) not in rates:
            continue
        k, n, (a, b), p99 = rates[level, v]
        within = "-" if v == base else ("yes" if lo <= k / n <= hi else "NO")
        print(f"| {level} | {v} | {n} | {100 * k / n:.0f} | {100 * a:.0f}-{100 * b:.0f} | {within} | {p99:.1f} |")
replays = sorted(out.glob("replay-*.jsonl"))
for path in replays:
    rows = [json.loads(line) for line in open(path) if line.strip().startswith("{")]
    if rows:
        worst = max(r["max_abs_diff"] for r in rows)
        mean = sum(r["mean_abs_diff"] * r["steps"] for r in rows) / max(1, sum(r["steps"] for r in rows))
        print(f"\nreplay of the {base} flights with the {path.stem.removeprefix('replay-')} model: {len(rows)} logs, "
              f"{sum(r['steps'] for r in rows)} steps, action difference max {worst:.4f}, mean {mean:.4f}")
PY
