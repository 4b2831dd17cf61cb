"""The faults ``runtime.programs.sitl --inject`` injects inside the runtime process (catalogue and
syntax: ``runtime.faults.catalogue``): ``inference-overrun`` and ``nan-action`` around the model step
(:class:`FaultyPolicy`), ``geofence`` by shrinking the watchdog's fence (:func:`shrink_geofence`,
:func:`shrink_geofence_at`).  Used only when an injection is asked for.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Callable, Iterable, Protocol

import numpy as np

from ..model import ModelOutput
from ..state import VehicleState
from ..watchdog import Watchdog
from .catalogue import FaultKind, Injection

log = logging.getLogger(__name__)

_NS_PER_S = 1_000_000_000
# An injected inference overrun blocks the step this long (s): far past any step trip limit, yet
# bounded, so the blocked worker thread ends and the process can exit after the trip.
INFERENCE_OVERRUN_S = 1.0
# geofence@T: the horizontal fence radius becomes this fraction of the vehicle's distance from the
# offboard start at T (T > 0: the vehicle is outside at once), or of the goal's distance from the
# vehicle (T = 0: the goal is outside the fence when the episode starts).
GEOFENCE_SHRINK_FRACTION = 0.5
GEOFENCE_MIN_RADIUS_M = 0.01


class _Policy(Protocol):
    def initial_hidden(self) -> np.ndarray: ...

    def step(self, gray: np.ndarray, depth: np.ndarray, state: np.ndarray, hidden: np.ndarray) -> ModelOutput: ...


class FaultyPolicy:
    """Wraps a policy model; from each injection's time on, its ``step`` misbehaves.

    ``inference-overrun``: the step sleeps INFERENCE_OVERRUN_S before answering (it runs in the
    flight loop's worker thread, as a hung ONNX Runtime call would).  ``nan-action``: the action
    is NaN.  Times count from :meth:`start` (ns, CLOCK_MONOTONIC).  ``injected`` records the
    monotonic time (s) each fault first acted.
    """

    def __init__(self, model: _Policy, injections: Iterable[Injection], clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self._model = model
        self._clock_ns = clock_ns
        self._at_s = {i.kind: i.at_s for i in injections if i.kind in (FaultKind.INFERENCE_OVERRUN, FaultKind.NAN_ACTION)}
        self._t0_ns: int | None = None
        self.injected: dict[FaultKind, float] = {}

    def start(self, t0_ns: int) -> None:
        """Offboard started at ``t0_ns``: the injection times count from here."""
        self._t0_ns = t0_ns

    def initial_hidden(self) -> np.ndarray:
        return self._model.initial_hidden()

    def step(self, gray: np.ndarray, depth: np.ndarray, state: np.ndarray, hidden: np.ndarray) -> ModelOutput:
        """The wrapped model's step, with the faults whose time has come."""
        if self._active(FaultKind.INFERENCE_OVERRUN):
            time.sleep(INFERENCE_OVERRUN_S)
        out = self._model.step(gray, depth, state, hidden)
        if self._active(FaultKind.NAN_ACTION):
            return ModelOutput(np.full_like(out.action, np.nan), out.hidden_next, out.latent)
        return out

    def _active(self, kind: FaultKind) -> bool:
        if kind not in self._at_s or self._t0_ns is None:
            return False
        now_ns = self._clock_ns()
        if now_ns - self._t0_ns < self._at_s[kind] * _NS_PER_S:
            return False
        if kind not in self.injected:
            self.injected[kind] = now_ns / _NS_PER_S
            log.warning("fault injected: %s", kind.value)
        return True


def shrink_geofence(watchdog: Watchdog, center_xy_enu_m: np.ndarray, point_enu_m: np.ndarray) -> float:
    """Set the watchdog's horizontal fence radius to GEOFENCE_SHRINK_FRACTION of ``point_enu_m``'s
    horizontal distance from ``center_xy_enu_m`` (local ENU, m); returns the new radius (m)."""
    distance_m = float(np.linalg.norm(np.asarray(point_enu_m[:2], dtype=np.float64) - np.asarray(center_xy_enu_m[:2])))
    radius_m = max(GEOFENCE_SHRINK_FRACTION * distance_m, GEOFENCE_MIN_RADIUS_M)
    watchdog.set_geofence_radius(radius_m)
    log.warning("fault injected: geofence radius now %.2f m (%.2f m to the point it must exclude)", radius_m, distance_m)
    return radius_m


async def shrink_geofence_at(watchdog: Watchdog, at_s: float, t0_ns: int, state: Callable[[], VehicleState]) -> float:
    """``geofence@at_s`` (``at_s`` > 0): ``at_s`` after ``t0_ns`` (ns, CLOCK_MONOTONIC), shrink the
    fence so that the vehicle is outside it (half its distance from the offboard start).

    Run as a task next to :meth:`FlightLoop.fly`.  ``geofence@0`` needs no task: shrink the fence
    around the goal with :func:`shrink_geofence` before ``fly``, whose goal check then refuses
    the episode.  Returns the monotonic time (s) of the injection.
    """
    delay_s = t0_ns / _NS_PER_S + at_s - time.monotonic()
    if delay_s > 0.0:
        await asyncio.sleep(delay_s)
    shrink_geofence(watchdog, watchdog.start_xy_enu_m, state().pos_enu_m)
    return time.monotonic()
