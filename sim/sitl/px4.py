"""PX4 flight modes as MAVLink carries them: main/sub custom modes and their HEARTBEAT encoding.

PX4 packs its mode into HEARTBEAT.custom_mode as ``main << 16 | sub << 24`` (sub only for AUTO);
DO_SET_MODE (176) carries main in param2 and sub in param3.  Names follow MAVSDK's
``telemetry.FlightMode`` (HOLD = AUTO.LOITER, ...), which is also how the trace's mode log reads.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum


class MainMode(IntEnum):
    """PX4 ``PX4_CUSTOM_MAIN_MODE``."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7


class AutoSubMode(IntEnum):
    """PX4 ``PX4_CUSTOM_SUB_MODE_AUTO`` (only meaningful with main mode AUTO)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6


_AUTO_NAMES = {
    AutoSubMode.READY: "READY",
    AutoSubMode.TAKEOFF: "TAKEOFF",
    AutoSubMode.LOITER: "HOLD",
    AutoSubMode.MISSION: "MISSION",
    AutoSubMode.RTL: "RETURN_TO_LAUNCH",
    AutoSubMode.LAND: "LAND",
}


class UnknownModeError(ValueError):
    """A custom mode that PX4 does not define."""


@dataclass(frozen=True)
class Px4Mode:
    """One PX4 flight mode: main mode and, for AUTO, its sub mode (0 otherwise)."""

    main: MainMode
    sub: int = 0

    @property
    def name(self) -> str:
        """MAVSDK's name of the mode (``HOLD`` for AUTO.LOITER, ``OFFBOARD``, ...)."""
        if self.main == MainMode.AUTO:
            return _AUTO_NAMES[AutoSubMode(self.sub)]
        return self.main.name

    @property
    def custom_mode(self) -> int:
        """HEARTBEAT.custom_mode: main << 16 | sub << 24."""
        return (int(self.main) << 16) | (int(self.sub) << 24)

    @classmethod
    def from_main_sub(cls, main: int, sub: int) -> Px4Mode:
        """Mode from DO_SET_MODE's param2 (main) and param3 (sub); raise UnknownModeError."""
        try:
            main_mode = MainMode(main)
        except ValueError as err:
            raise UnknownModeError(f"PX4 has no main mode {main}") from err
        if main_mode != MainMode.AUTO:
            return cls(main_mode, 0)
        try:
            return cls(main_mode, int(AutoSubMode(sub)))
        except ValueError as err:
            raise UnknownModeError(f"PX4 has no AUTO sub mode {sub}") from err

    @classmethod
    def from_custom_mode(cls, custom_mode: int) -> Px4Mode:
        """Inverse of :attr:`custom_mode`."""
        return cls.from_main_sub((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)

    def __str__(self) -> str:
        return self.name


HOLD = Px4Mode(MainMode.AUTO, AutoSubMode.LOITER)
TAKEOFF = Px4Mode(MainMode.AUTO, AutoSubMode.TAKEOFF)
LAND = Px4Mode(MainMode.AUTO, AutoSubMode.LAND)
OFFBOARD = Px4Mode(MainMode.OFFBOARD)
POSCTL = Px4Mode(MainMode.POSCTL)
ALTCTL = Px4Mode(MainMode.ALTCTL)
MANUAL = Px4Mode(MainMode.MANUAL)
RETURN = Px4Mode(MainMode.AUTO, AutoSubMode.RTL)
