"""Latency statistics of the flight loop (milliseconds), bounded in memory."""

from __future__ import annotations

from collections import deque

import numpy as np

# At 15 Hz this is over an hour of steps; older samples fall out of the percentiles.
MAX_SAMPLES = 65_536


class LatencyStats:
    """Samples (ms) of one quantity; p50/p99 over the most recent ``MAX_SAMPLES``."""

    def __init__(self) -> None:
        self._samples: deque[float] = deque(maxlen=MAX_SAMPLES)

    def add(self, ms: float) -> None:
        self._samples.append(float(ms))

    def __len__(self) -> int:
        return len(self._samples)

    def summary(self) -> dict[str, float | int | None]:
        """{p50, p99, max, n}; percentiles are None before the first sample."""
        if not self._samples:
            return {"p50": None, "p99": None, "max": None, "n": 0}
        values = np.fromiter(self._samples, dtype=np.float64)
        p50, p99 = np.percentile(values, [50, 99])
        return {"p50": round(float(p50), 3), "p99": round(float(p99), 3), "max": round(float(values.max()), 3), "n": len(values)}


class StageTimes:
    """One :class:`LatencyStats` per named stage."""

    def __init__(self) -> None:
        self.stages: dict[str, LatencyStats] = {}

    def add(self, stages_ms: dict[str, float]) -> None:
        for name, ms in stages_ms.items():
            self.stages.setdefault(name, LatencyStats()).add(ms)

    def summary(self) -> dict[str, dict]:
        return {name: stats.summary() for name, stats in self.stages.items()}
