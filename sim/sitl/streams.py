"""Periodic telemetry streams and their rates, changeable with SET_MESSAGE_INTERVAL (511).

Default rates are PX4's "onboard" MAVLink mode (the link a companion computer uses), trimmed to
what MAVSDK's telemetry reads.  Deadlines advance by whole periods (no drift); a stream that
fell more than a period behind is re-phased rather than burst.
"""

from __future__ import annotations

import logging

from pymavlink.dialects.v20 import common as mavlink

log = logging.getLogger(__name__)

DEFAULT_RATES_HZ: dict[int, float] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 50.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 25.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 50.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 25.0,
    mavlink.MAVLINK_MSG_ID_ODOMETRY: 30.0,
    mavlink.MAVLINK_MSG_ID_ALTITUDE: 10.0,
}


class StreamScheduler:
    """Which streamed messages are due at a time (time.monotonic, s)."""

    def __init__(self, t_s: float, max_rate_hz: float, rates_hz: dict[int, float] = DEFAULT_RATES_HZ) -> None:
        self._max_rate_hz = max_rate_hz
        self._defaults = dict(rates_hz)
        self._period_s = {msg_id: 1.0 / hz for msg_id, hz in rates_hz.items()}
        # Everything goes out on the first tick: a client connecting sees the full state at once.
        self._next_s = {msg_id: t_s for msg_id in rates_hz}

    def knows(self, msg_id: int) -> bool:
        return msg_id in self._defaults

    def set_interval(self, msg_id: int, interval_us: float, t_s: float) -> bool:
        """SET_MESSAGE_INTERVAL semantics: -1 stops, 0 restores the default, > 0 is the period
        (limited to the physics rate).  False if the message is not one this vehicle streams."""
        if msg_id not in self._defaults:
            return False
        if interval_us < 0:
            self._period_s.pop(msg_id, None)
            self._next_s.pop(msg_id, None)
            log.info("stream %d stopped", msg_id)
            return True
        period_s = 1.0 / self._defaults[msg_id] if interval_us == 0 else max(interval_us * 1e-6, 1.0 / self._max_rate_hz)
        self._period_s[msg_id] = period_s
        self._next_s[msg_id] = t_s
        log.info("stream %d at %.1f Hz", msg_id, 1.0 / period_s)
        return True

    def due(self, t_s: float) -> list[int]:
        """Message ids due at t_s; their deadlines advance by one period each."""
        ready = []
        for msg_id, next_s in self._next_s.items():
            if t_s >= next_s:
                ready.append(msg_id)
                period_s = self._period_s[msg_id]
                next_s += period_s
                self._next_s[msg_id] = next_s if next_s > t_s else t_s + period_s
        return ready
