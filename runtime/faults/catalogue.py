"""Fault injection for the SITL fault tests (DESIGN §3: the watchdog is tested by injecting faults).

An injection is written ``KIND@SECONDS``: the fault starts SECONDS after offboard started and
lasts for the rest of the flight.  Each kind is injected where it really happens:

- in the SITL vehicle (``python -m sim.sitl --inject``, times from the vehicle's own OFFBOARD
  entry): ``camera-stall``, ``camera-garbage``, ``camera-blackout``, ``telemetry-loss``,
  ``pilot-takeover``, ``offboard-refused`` (only ``@0``: the vehicle refuses OFFBOARD when asked),
  ``vehicle-stuck`` (the vehicle stops following setpoints, without a collision);
- in the runtime (``python -m runtime.programs.sitl --inject``, times from the start of
  :meth:`runtime.flight.FlightLoop.fly`; hooks in ``runtime.faults.injection``):
  ``inference-overrun`` and ``nan-action`` around the model step, ``geofence`` (the watchdog's
  fence shrinks);
- by ``cmnav sitl`` itself, SECONDS after the camera world saw the autopilot enter OFFBOARD:
  ``runtime-kill`` (SIGKILL of the runtime process: nothing it does survives; the autopilot's
  offboard-loss failsafe decides) and ``runtime-stop`` (SIGTERM, what systemd and a shutdown send:
  the runtime's own stop handling, ``runtime.programs.stop``, brakes to a hover, then commands Hold).

With an external autopilot (``cmnav sitl --autopilot``, PX4 SITL) the world follower injects the
camera faults on the frames it serves (``sim.follower.faults`` says which vehicle faults it cannot
do, and why); the runtime's and the orchestrator's faults work as with our vehicle.

Nothing is injected unless asked for explicitly: without ``--inject`` the runtime uses the
model and the watchdog as they are, with no extra code on the path.  This module is the
catalogue and the syntax only (standard library), so the SITL vehicle and ``cmnav`` can use it
without loading the runtime.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from typing import Iterable


class FaultKind(str, Enum):
    CAMERA_STALL = "camera-stall"  # frames stop
    CAMERA_GARBAGE = "camera-garbage"  # NaN/inf/negative depth, wrong-shape and future-stamped frames
    CAMERA_BLACKOUT = "camera-blackout"  # depth 100 % invalid
    TELEMETRY_LOSS = "telemetry-loss"  # the vehicle -> runtime direction of the link goes silent
    PILOT_TAKEOVER = "pilot-takeover"  # the RC pilot switches to Position mode
    OFFBOARD_REFUSED = "offboard-refused"  # the vehicle refuses DO_SET_MODE OFFBOARD
    INFERENCE_OVERRUN = "inference-overrun"  # the model step blocks past the deadline
    NAN_ACTION = "nan-action"  # the model step returns NaN
    GEOFENCE = "geofence"  # the fence shrinks: the vehicle (or the goal) is outside it
    RUNTIME_KILL = "runtime-kill"  # SIGKILL of the runtime process
    RUNTIME_STOP = "runtime-stop"  # SIGTERM to the runtime process: its graceful stop (hover, then Hold)
    VEHICLE_STUCK = "vehicle-stuck"  # the vehicle stops following setpoints (motor failure, snagged frame)


class FaultSite(str, Enum):
    VEHICLE = "vehicle"
    RUNTIME = "runtime"
    ORCHESTRATOR = "orchestrator"


FAULT_SITE: dict[FaultKind, FaultSite] = {
    FaultKind.CAMERA_STALL: FaultSite.VEHICLE,
    FaultKind.CAMERA_GARBAGE: FaultSite.VEHICLE,
    FaultKind.CAMERA_BLACKOUT: FaultSite.VEHICLE,
    FaultKind.TELEMETRY_LOSS: FaultSite.VEHICLE,
    FaultKind.PILOT_TAKEOVER: FaultSite.VEHICLE,
    FaultKind.OFFBOARD_REFUSED: FaultSite.VEHICLE,
    FaultKind.INFERENCE_OVERRUN: FaultSite.RUNTIME,
    FaultKind.NAN_ACTION: FaultSite.RUNTIME,
    FaultKind.GEOFENCE: FaultSite.RUNTIME,
    FaultKind.RUNTIME_KILL: FaultSite.ORCHESTRATOR,
    FaultKind.RUNTIME_STOP: FaultSite.ORCHESTRATOR,
    FaultKind.VEHICLE_STUCK: FaultSite.VEHICLE,
}


# The faults of the camera itself: what reaches the runtime over the camera link.
CAMERA_FAULTS: frozenset[FaultKind] = frozenset({FaultKind.CAMERA_STALL, FaultKind.CAMERA_GARBAGE, FaultKind.CAMERA_BLACKOUT})


class InjectionError(ValueError):
    """An ``--inject`` value that is not ``KIND@SECONDS`` with a known kind and a valid time."""


@dataclass(frozen=True)
class Injection:
    """Fault ``kind`` from ``at_s`` seconds after offboard start to the end of the flight."""

    kind: FaultKind
    at_s: float

    def __str__(self) -> str:
        return f"{self.kind.value}@{self.at_s:g}"

    @property
    def site(self) -> FaultSite:
        return FAULT_SITE[self.kind]


def parse_injection(text: str, sites: Iterable[FaultSite] = tuple(FaultSite)) -> Injection:
    """``"camera-stall@2"`` -> Injection; raise :class:`InjectionError` naming the problem and
    the kinds injected at ``sites``."""
    allowed = sorted(kind.value for kind, site in FAULT_SITE.items() if site in set(sites))
    kind_text, sep, at_text = text.partition("@")
    if not sep:
        raise InjectionError(f"--inject {text!r}: expected KIND@SECONDS, e.g. camera-stall@2 (kinds: {', '.join(allowed)})")
    if kind_text not in allowed:
        raise InjectionError(f"--inject {text!r}: unknown fault kind {kind_text!r} here; expected one of {', '.join(allowed)}")
    try:
        at_s = float(at_text)
    except ValueError:
        at_s = math.nan
    if not (math.isfinite(at_s) and at_s >= 0.0):
        raise InjectionError(f"--inject {text!r}: SECONDS must be a number >= 0 (seconds after offboard start)")
    kind = FaultKind(kind_text)
    if kind == FaultKind.OFFBOARD_REFUSED and at_s != 0.0:
        raise InjectionError(f"--inject {text!r}: offboard-refused happens when the runtime asks for offboard; write offboard-refused@0")
    if kind == FaultKind.RUNTIME_KILL and at_s == 0.0:
        raise InjectionError(f"--inject {text!r}: runtime-kill needs a time after offboard start, e.g. runtime-kill@2")
    return Injection(kind, at_s)
