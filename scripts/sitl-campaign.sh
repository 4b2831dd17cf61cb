#!/usr/bin/env bash
# Fly one model in SITL over many seeds and levels and print the outcome table:
#   bash scripts/sitl-campaign.sh MODEL.onnx "0 3" 20 [OUT_DIR]
# (levels, seeds per level).  Each flight is `cmnav sitl --json`; the summaries go to
# OUT_DIR/summaries.jsonl (default runs/sitl-campaign/<model name>).  Besides outcomes it counts
# the watchdog's trips: those in flights that did not crash (false alarms: nothing is injected
# here), and the crashes the runtime caught within 1.5 s (tracking or vehicle_fault).
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
all_trips = collections.Counter()
for r in rows:
    by_level[r["level"]].append(r)
print("| level | flights | success % | crash % | timeout % | other | time_s (success, median) | step p99 ms (median) | watchdog trips | trips without a crash | crashes caught <= 1.5 s | crash_detect_ms (median) | tracking error sustained, m/s (max, no crash) |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
for level, rs in sorted(by_level.items()):
    n = len(rs)
    count = collections.Counter(r["outcome"] for r in rs)
    times = [r["time_s"] for r in rs if r["outcome"] == "success"]
    p99 = [r["step_ms"]["p99"] for r in rs if (r.get("step_ms") or {}).get("p99") is not None]
    other = n - count["success"] - count["crash"] - count["timeout"]
    trips = sum(len(r.get("watchdog_trips", [])) for r in rs)
    # A trip in a flight that did not crash is a false alarm unless a fault was injected.
    false_trips = [t["cause"] for r in rs if r["outcome"] != "crash" for t in r.get("watchdog_trips", [])]
    detect = [r["crash_detect_ms"] for r in rs if r["outcome"] == "crash" and r.get("crash_detect_ms") is not None]
    caught = sum(ms <= 1500.0 for ms in detect)
    # The largest velocity-tracking error a flight held for a whole tracking window: the margin to
    # the watchdog's bound (tracking_error_max_m_s) in flights that did not crash.
    peaks = [r["tracking_error_peak_m_s"] for r in rs if r["outcome"] != "crash" and r.get("tracking_error_peak_m_s") is not None]
    print(f"| {level} | {n} | {100 * count['success'] / n:.0f} | {100 * count['crash'] / n:.0f} | {100 * count['timeout'] / n:.0f} | "
          f"{other} | {statistics.median(times) if times else float('nan'):.1f} | {statistics.median(p99) if p99 else float('nan'):.1f} | {trips} | "
          f"{len(false_trips)} | {caught}/{count['crash']} | {statistics.median(detect) if detect else float('nan'):.0f} | "
          f"{max(peaks) if peaks else float('nan'):.2f} |")
    all_trips.update(t["cause"] for r in rs for t in r.get("watchdog_trips", []))
print("watchdog trips by cause:", dict(all_trips) or "none")
PY
