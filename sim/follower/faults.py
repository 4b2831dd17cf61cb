"""Which vehicle faults the world follower can inject with an external autopilot, and why not the others.

The follower owns only the camera: it renders and serves the frames, so it injects the camera
faults (``runtime.faults.catalogue.CAMERA_FAULTS``) with our vehicle's own hooks
(``sim.sitl.faults.VehicleFaults.camera_frame``).  The other vehicle faults need the autopilot's
side of the link or its dynamics, which belong to PX4 here.  Standard library and the catalogue
only: ``cmnav sitl`` refuses them before it starts anything, where pymavlink and torch need not load.
"""

from __future__ import annotations

from collections.abc import Iterable

from runtime.faults.catalogue import CAMERA_FAULTS, FaultKind, FaultSite, Injection, InjectionError

NOT_WITH_AN_AUTOPILOT: dict[FaultKind, str] = {
    FaultKind.TELEMETRY_LOSS: "it silences the autopilot's MAVLink to the runtime, and that link is PX4's own, "
    "not the follower's",
    FaultKind.PILOT_TAKEOVER: "it is an RC mode switch on the autopilot; the follower only listens to PX4",
    FaultKind.OFFBOARD_REFUSED: "PX4 itself decides whether it accepts OFFBOARD; the follower cannot make it refuse",
    FaultKind.VEHICLE_STUCK: "PX4's dynamics (SIH) fly the vehicle; the follower cannot make it ignore setpoints",
}


def follower_injection_problem(injection: Injection) -> str | None:
    """Why the follower cannot inject ``injection`` with an external autopilot (one line naming
    the fault, the reason and the way out), or None when it can or when it is not the vehicle's."""
    if injection.site != FaultSite.VEHICLE or injection.kind in CAMERA_FAULTS:
        return None
    reason = NOT_WITH_AN_AUTOPILOT.get(injection.kind, "the follower injects only the camera faults")
    return (f"--inject {injection}: not with an external autopilot: {reason}; fly it against our SITL vehicle "
            f"(cmnav sitl without --autopilot). With --autopilot: {', '.join(sorted(k.value for k in CAMERA_FAULTS))}, "
            "the runtime's faults and runtime-kill / runtime-stop")  # fmt: skip


def check_follower_injections(injections: Iterable[Injection]) -> tuple[Injection, ...]:
    """The injections the follower applies itself (the camera faults); raise InjectionError for
    any it cannot do with an external autopilot or that happens elsewhere (runtime, orchestrator)."""
    injections = tuple(injections)
    for injection in injections:
        if injection.site != FaultSite.VEHICLE:
            raise InjectionError(f"--inject {injection}: {injection.kind.value} is injected by the {injection.site.value}, "
                                 "not by the world follower (cmnav sitl passes it there)")  # fmt: skip
        if (problem := follower_injection_problem(injection)) is not None:
            raise InjectionError(problem)
    return injections
