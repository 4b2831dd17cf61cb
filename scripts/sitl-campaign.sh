#!/usr/bin/env bash
# Fly one model in SITL over many seeds and levels and print the outcome table:
#   bash scripts/sitl-campaign.sh MODEL.onnx "0 3" 20 [OUT_DIR]
# (levels, seeds per level).  Each flight is `cmnav sitl --json`; the summaries go to
# OUT_DIR/summaries.jsonl (default runs/sitl-campaign/<model name>).
set -euo pipefail
MODEL=$1
LEVELS=${2:-"0"}
SEEDS=${3:-20}
OUT=${4:-runs/sitl-campaign/$(basename "$MODEL" .onnx)}
CMNAV=${CMNAV:-.venv/bin/cmnav}
TIMEOUT_S=${TIMEOUT_S:-20}  # offboard time limit per flight (training episodes last 10 s)
mkdir -p "$OUT"
: > "$OUT/summaries.jsonl"
for level in $LEVELS; do
  for seed in $(seq 0 $((SEEDS - 1))); do
    "$CMNAV" sitl --model "$MODEL" --level "$level" --seed "$seed" --timeout "$TIMEOUT_S" --out "$OUT/runs" --json 2>>"$OUT/sitl.log" \
      | tail -n 1 >> "$OUT/summaries.jsonl" || true
  done
done
.venv/bin/python - "$OUT/summaries.jsonl" <<'PY'
import collections, json, statistics, sys
rows = [json.loads(line) for line in open(sys.argv[1]) if line.strip().startswith("{")]
by_level = collections.defaultdict(list)
for r in rows:
    by_level[r["level"]].append(r)
print("| level | flights | success % | crash % | timeout % | other | time_s (success, median) | step p99 ms (median) | watchdog trips |")
print("|---|---|---|---|---|---|---|---|---|")
for level, rs in sorted(by_level.items()):
    n = len(rs)
    count = collections.Counter(r["outcome"] for r in rs)
    times = [r["time_s"] for r in rs if r["outcome"] == "success"]
    p99 = [r["step_ms"]["p99"] for r in rs if r.get("step_ms")]
    other = n - count["success"] - count["crash"] - count["timeout"]
    trips = sum(len(r.get("watchdog_trips", [])) for r in rs)
    print(f"| {level} | {n} | {100 * count['success'] / n:.0f} | {100 * count['crash'] / n:.0f} | {100 * count['timeout'] / n:.0f} | "
          f"{other} | {statistics.median(times) if times else float('nan'):.1f} | {statistics.median(p99) if p99 else float('nan'):.1f} | {trips} |")
PY
