"""The few PX4 parameters this SITL vehicle uses, served over the MAVLink parameter protocol so
that MAVSDK's ``action.set_takeoff_altitude`` / ``get_takeoff_altitude`` and param reads work.

PX4 encodes integer parameters "bytewise": the int32's bytes travel in PARAM_VALUE's float field
(MAVSDK decodes them that way for PX4, and AUTOPILOT_VERSION advertises it).
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

log = logging.getLogger(__name__)

REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
INT32 = mavlink.MAV_PARAM_TYPE_INT32


class ParamError(ValueError):
    """Unknown parameter name or a value of the wrong type."""


# COM_OBL_RC_ACT, PX4's offboard-loss failsafe action.  0-2 need RC sticks: a vehicle without RC
# input cannot fly them, and PX4 then descends and lands where it is (its failsafe flight task).
OBL_POSITION, OBL_ALTITUDE, OBL_MANUAL, OBL_RETURN, OBL_LAND, OBL_HOLD, OBL_TERMINATE, OBL_DISARM = range(8)
OBL_ACTIONS = {OBL_POSITION: "Position", OBL_ALTITUDE: "Altitude", OBL_MANUAL: "Manual", OBL_RETURN: "Return",
               OBL_LAND: "Land", OBL_HOLD: "Hold", OBL_TERMINATE: "Terminate", OBL_DISARM: "Disarm"}  # fmt: skip
# Integer parameters with a closed set of values (PX4 rejects others too).
_ALLOWED = {"COM_OBL_RC_ACT": OBL_ACTIONS}


@dataclass
class Param:
    name: str
    value: float | int
    param_type: int


def _defaults(takeoff_alt_m: float) -> list[Param]:
    return [
        Param("COM_DISARM_LAND", 2.0, REAL32),  # s landed before auto-disarm
        Param("COM_DISARM_PRFLT", 10.0, REAL32),  # s armed without take-off before auto-disarm
        Param("COM_OBL_RC_ACT", OBL_POSITION, INT32),  # offboard-loss failsafe action (OBL_ACTIONS)
        Param("COM_OF_LOSS_T", 1.0, REAL32),  # s without offboard setpoints before the failsafe
        Param("MIS_TAKEOFF_ALT", float(takeoff_alt_m), REAL32),  # m above home
        Param("MPC_LAND_SPEED", 0.7, REAL32),  # m/s
        Param("MPC_TKO_SPEED", 1.5, REAL32),  # m/s
        Param("NAV_MC_ALT_RAD", 0.8, REAL32),  # m: the take-off is complete (-> Hold) within this of its height
        Param("SYS_HITL", 0, INT32),
    ]


class ParamTable:
    """Name -> value, in PX4's order (sorted by name) so indices are stable."""

    def __init__(self, takeoff_alt_m: float) -> None:
        self._params = sorted(_defaults(takeoff_alt_m), key=lambda p: p.name)
        self._by_name = {p.name: p for p in self._params}

    def __len__(self) -> int:
        return len(self._params)

    def __getitem__(self, name: str) -> float:
        return float(self._by_name[name].value)

    def index_of(self, name: str) -> int:
        return self._params.index(self._by_name[name])

    def find(self, name: str, index: int) -> Param:
        """By name, or by index when the name is empty (PARAM_REQUEST_READ semantics)."""
        if name:
            if name not in self._by_name:
                raise ParamError(f"unknown parameter {name!r}")
            return self._by_name[name]
        if not 0 <= index < len(self._params):
            raise ParamError(f"parameter index {index} out of range [0, {len(self._params)})")
        return self._params[index]

    def all(self) -> list[Param]:
        return list(self._params)

    def set_from_wire(self, name: str, wire_value: float, param_type: int) -> Param:
        """PARAM_SET: decode ``wire_value`` (bytewise for integers) and store it."""
        param = self.find(name, -1)
        if param_type != param.param_type:
            raise ParamError(f"{name} has MAV_PARAM_TYPE {param.param_type}, PARAM_SET sent {param_type}")
        if param.param_type == INT32:
            value = struct.unpack("<i", struct.pack("<f", wire_value))[0]
            if name in _ALLOWED and value not in _ALLOWED[name]:
                raise ParamError(f"{name}={value} is not one of {sorted(_ALLOWED[name])}")
            param.value = value
        else:
            if not math.isfinite(wire_value):
                raise ParamError(f"{name}={wire_value} is not finite")
            param.value = float(wire_value)
        log.info("parameter %s set to %s", name, param.value)
        return param

    @staticmethod
    def wire_value(param: Param) -> float:
        """PARAM_VALUE.param_value of ``param`` (bytewise for integers)."""
        if param.param_type == INT32:
            return struct.unpack("<f", struct.pack("<i", int(param.value)))[0]
        return float(param.value)
