#!/usr/bin/env bash
# The one command for a lent GPU machine (torch, onnx, onnxruntime, numpy; no internet; at most
# 10 minutes a command): `bash scripts/gpu-pipeline.sh`, repeated until it says "done".
#
# Each call runs `cmnav pipeline` for at most CALL_MINUTES and stops checkpointed; the next call
# continues from runs/pipeline-gpu (kept on the machine while it stays warm).  When the run is
# complete, what a commit needs goes to $OUT (at most 8 files of <= 16 MiB): the encoder's fp16
# shards as they are, everything else small in one tarball.  model.onnx (about 60 MB at paper
# size) is not brought back: re-export it from the checkpoints with `cmnav export`, which checks
# parity again.
set -euo pipefail
MINUTES=${MINUTES:-24}
CALL_MINUTES=${CALL_MINUTES:-8.5}
RUN=${RUN:-runs/pipeline-gpu}
mkdir -p "$RUN"
status=0
python -m cmnav pipeline --device cuda --minutes "$MINUTES" --call-minutes "$CALL_MINUTES" --out "$RUN" \
  2>&1 | tee -a "$RUN/pipeline.log" | grep -v '^train \|^eval policy:\|^dataset ' || status=${PIPESTATUS[0]}
if [ "$status" = 3 ]; then
  echo "not done yet: run scripts/gpu-pipeline.sh again"
  exit 0
elif [ "$status" != 0 ]; then
  echo "pipeline failed (exit $status); log: $RUN/pipeline.log"
  tail -n 40 "$RUN/pipeline.log"
  exit "$status"
fi
if [ -n "${OUT:-}" ]; then
  cp "$RUN"/encoder/weights-*.pt "$OUT"/
  tar czf "$OUT/pipeline-results.tar.gz" -C "$RUN" --exclude='encoder/weights-*.pt' --exclude='*/train_state.pt' \
    --exclude=data --exclude='*.onnx' .
  ls -la "$OUT"
fi
echo "done: $RUN/MODEL_CARD.md"
