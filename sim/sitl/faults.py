"""Faults the SITL vehicle injects on itself (``python -m sim.sitl --inject KIND@SECONDS``), where
they happen on a real vehicle.  Kinds and syntax: ``runtime.faults.catalogue``.  Times count from the
vehicle's own first OFFBOARD entry; ``offboard-refused`` (only ``@0``) holds from the start.

- ``camera-stall``: no frame leaves the camera any more (the link stays open and silent).
- ``camera-garbage``: every frame is garbage, in turn: depth of random float32 bits (negative,
  NaN, inf, huge) with noise for gray; a frame of another resolution; a good image stamped
  FUTURE_STAMP_S in the future (a runtime that trusted it would think its camera fresh).
- ``camera-blackout``: depth 100 % invalid (0.0, as the sensor reports), gray unchanged.
- ``telemetry-loss``: the vehicle -> companion direction of the link goes silent: no stream,
  no HEARTBEAT, no COMMAND_ACK, no STATUSTEXT (a dead TX line, a crashed MAVLink instance).
  What the runtime sends still arrives, MAVSDK's 20 Hz setpoint re-sends included, so PX4's
  offboard-loss failsafe never fires and only the runtime's watchdog can stop the flight.
  A loss of both directions is, for the vehicle, the ``runtime-kill`` case (setpoints stop).
- ``pilot-takeover``: the RC pilot flips the mode switch to Position mode (sticks centred).
- ``offboard-refused``: DO_SET_MODE OFFBOARD is DENIED ("mode not available").
- ``vehicle-stuck``: the vehicle stops following setpoints without a collision and without a word
  (a snagged frame, a motor that lost thrust): in OFFBOARD its velocity controller gets zero
  velocity and no yaw rate whatever the setpoint, so it brakes to a stop and stays there, armed,
  telemetry flowing; only the runtime's tracking check can tell.  The autopilot's own modes (Hold,
  Land) still fly, so the test flight can land afterwards.

The world follower (``python -m sim.follower --inject``, flying an external autopilot) applies the
same camera hooks to the frames it serves, its times counted from the autopilot's first OFFBOARD
as the follower sees it in HEARTBEAT (``sim.follower.faults``).

Threads: the camera hooks run in the render thread, the others in the physics thread; they share
only the OFFBOARD entry time (a float written once) and ``injected`` (one key per kind).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import replace

import numpy as np

from runtime.camera.frame import Frame
from runtime.contract.images import invalid_depth_fraction
from runtime.faults.catalogue import CAMERA_FAULTS, FaultKind, FaultSite, Injection, InjectionError

log = logging.getLogger(__name__)

FUTURE_STAMP_S = 10.0
_NS_PER_S = 1_000_000_000
_GARBAGE_FORMS = ("bits", "shape", "future")


class VehicleFaults:
    """The vehicle's injection schedule and the hooks that apply it."""

    def __init__(self, injections: Iterable[Injection], seed: int = 0) -> None:
        injections = list(injections)
        for injection in injections:
            if injection.site != FaultSite.VEHICLE:
                raise InjectionError(f"--inject {injection}: {injection.kind.value} is not injected by the SITL vehicle")
        self._at_s = {i.kind: i.at_s for i in injections}
        self._t_offboard_s: float | None = None
        self._rng = np.random.default_rng(seed)
        self._garbage_sent = 0
        self._pilot_switched = False
        self.injected: dict[FaultKind, float] = {}  # kind -> time.monotonic() when it first acted

    @property
    def camera_faults(self) -> bool:
        return any(k in self._at_s for k in CAMERA_FAULTS)

    @property
    def refuses_offboard(self) -> bool:
        return FaultKind.OFFBOARD_REFUSED in self._at_s

    def note_offboard(self, t_s: float) -> None:
        """The vehicle entered OFFBOARD at ``t_s`` (time.monotonic); only the first entry counts."""
        if self._t_offboard_s is None:
            self._t_offboard_s = t_s
            log.info("fault schedule starts: %s", ", ".join(f"{k.value}@{v:g}" for k, v in self._at_s.items()) or "none")

    def active(self, kind: FaultKind, t_s: float) -> bool:
        """Is ``kind`` injected and due at ``t_s``?  Records the first time it acts."""
        if kind not in self._at_s:
            return False
        if kind != FaultKind.OFFBOARD_REFUSED and (self._t_offboard_s is None or t_s < self._t_offboard_s + self._at_s[kind]):
            return False
        if kind not in self.injected:
            self.injected[kind] = t_s
            log.warning("fault injected: %s", kind.value)
        return True

    # ---- render thread --------------------------------------------------------------------

    def camera_frame(self, frame: Frame, t_s: float) -> Frame | None:
        """What the camera delivers instead of ``frame`` at ``t_s``: None = nothing (stalled)."""
        if self.active(FaultKind.CAMERA_STALL, t_s):
            return None
        if self.active(FaultKind.CAMERA_GARBAGE, t_s):
            return self._garbage(frame)
        if self.active(FaultKind.CAMERA_BLACKOUT, t_s):
            depth = np.zeros_like(frame.depth_m)
            return replace(frame, depth_m=depth, meta={**frame.meta, "invalid_depth_frac": 1.0, "fault": "camera-blackout"})
        return frame

    def _garbage(self, frame: Frame) -> Frame:
        form = _GARBAGE_FORMS[self._garbage_sent % len(_GARBAGE_FORMS)]
        self._garbage_sent += 1
        height, width = frame.depth_m.shape
        t_capture_ns = frame.t_capture_ns
        if form == "bits":
            depth = self._rng.integers(0, 2**32, size=(height, width), dtype=np.uint32).view(np.float32)
            depth[: height // 4] = np.nan
            depth[height // 4 : height // 2, : width // 2] = np.inf
            depth[height // 4 : height // 2, width // 2 :] = -np.inf
            gray = self._rng.integers(0, 256, size=(height, width), dtype=np.uint8)
        elif form == "shape":
            depth = np.full((height // 2, width // 3), 2.0, dtype=np.float32)
            gray = np.full(depth.shape, 128, dtype=np.uint8)
        else:
            depth, gray = frame.depth_m, frame.gray_u8
            t_capture_ns += int(FUTURE_STAMP_S * _NS_PER_S)
        meta = {"invalid_depth_frac": invalid_depth_fraction(depth), "fault": f"camera-garbage:{form}"}
        return Frame(t_capture_ns=t_capture_ns, depth_m=depth, gray_u8=gray, seq=frame.seq, meta=meta)

    # ---- physics thread -------------------------------------------------------------------

    def telemetry_lost(self, t_s: float) -> bool:
        return self.active(FaultKind.TELEMETRY_LOSS, t_s)

    def pilot_takes_over(self, t_s: float) -> bool:
        """True once, when the pilot's mode switch is due."""
        if self._pilot_switched or not self.active(FaultKind.PILOT_TAKEOVER, t_s):
            return False
        self._pilot_switched = True
        return True

    def stuck(self, t_s: float) -> bool:
        """True while the vehicle ignores its setpoints (``vehicle-stuck``)."""
        return self.active(FaultKind.VEHICLE_STUCK, t_s)

    def offboard_allowed(self, t_s: float) -> bool:
        """The commander asks before entering OFFBOARD; False = refuse."""
        return not self.active(FaultKind.OFFBOARD_REFUSED, t_s)
