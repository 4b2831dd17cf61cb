"""The autopilot's own word: STATUSTEXT messages as the runtime keeps them (pure data, no MAVSDK).

PX4 announces what it detects itself in STATUSTEXT (collision, failure detector, battery, EKF):
severity CRITICAL or worse means the vehicle is no longer fit to fly the policy, and the watchdog
ends the episode on it (``vehicle_fault``).  Severities are MAVLink's MAV_SEVERITY names.
"""

from __future__ import annotations

from dataclasses import dataclass

# MAV_SEVERITY, most severe first (the MAVLink values 0..7).
SEVERITIES = ("EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING", "NOTICE", "INFO", "DEBUG")
FAULT_SEVERITIES = frozenset(SEVERITIES[: SEVERITIES.index("CRITICAL") + 1])
# How many of the latest messages a VehicleState snapshot carries.
STATUS_TEXTS_KEPT = 16


@dataclass(frozen=True)
class StatusText:
    """One STATUSTEXT: ``seq`` counts messages from 1 in order of receipt, ``t_ns`` is the
    receive time (CLOCK_MONOTONIC), ``severity`` a MAV_SEVERITY name."""

    seq: int
    t_ns: int
    severity: str
    text: str

    @property
    def is_fault(self) -> bool:
        """Severity CRITICAL or worse: the autopilot says the vehicle is in trouble."""
        return self.severity in FAULT_SEVERITIES


def append_status_text(kept: tuple[StatusText, ...], t_ns: int, severity: str, text: str) -> tuple[StatusText, ...]:
    """``kept`` with a new message at the end, the oldest dropped beyond STATUS_TEXTS_KEPT."""
    seq = kept[-1].seq + 1 if kept else 1
    return (*kept, StatusText(seq, t_ns, severity, text))[-STATUS_TEXTS_KEPT:]
