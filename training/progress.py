"""A dependency-free progress line for long jobs (the GPU machine has no tqdm): count, rate,
ETA and extra values, redrawn in place on a terminal and printed every few seconds otherwise."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    def __init__(self, total: int, desc: str, unit: str = "it", stream: TextIO | None = None, every_s: float = 5.0,
                 initial: int = 0) -> None:
        self.total, self.desc, self.unit = total, desc, unit
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty()
        self.every_s = 0.2 if self.tty else every_s
        self.count = self.initial = initial  # initial: work already done (a resumed run)
        self.t0 = time.monotonic()
        self._last_draw = float("-inf")
        self._drawn_count = -1
        self.values: dict[str, str] = {}

    def update(self, n: int = 1, **values: float | str) -> None:
        self.count += n
        self.values.update({k: (f"{v:.4g}" if isinstance(v, float) else str(v)) for k, v in values.items()})
        now = time.monotonic()
        if now - self._last_draw >= self.every_s or self.count >= self.total:
            self._last_draw = now
            self._draw(now)

    def _draw(self, now: float) -> None:
        self._drawn_count = self.count
        elapsed = max(now - self.t0, 1e-9)
        rate = (self.count - self.initial) / elapsed
        eta = (self.total - self.count) / rate if rate > 0 else float("inf")
        extra = " ".join(f"{k}={v}" for k, v in self.values.items())
        line = (f"{self.desc}: {self.count}/{self.total} {self.unit} ({100.0 * self.count / max(self.total, 1):.0f}%) "
                f"{rate:.1f} {self.unit}/s elapsed {elapsed:.0f}s eta {eta:.0f}s {extra}")  # fmt: skip
        self.stream.write(("\r" + line + "\x1b[K") if self.tty else line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self._drawn_count != self.count:
            self._draw(time.monotonic())
        if self.tty:
            self.stream.write("\n")
