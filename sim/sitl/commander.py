"""PX4's commander, reduced to what a companion computer can observe: arming rules, mode
switching, take-off and landing sequences, land detection and auto-disarm, the offboard-loss
failsafe, and what each mode asks of the velocity controller.

Pure logic: every method takes the time (time.monotonic, s) and the vehicle's
:class:`~sim.sitl.kinematics.Kinematics`; nothing here does I/O.  Results are MAV_RESULT values;
notable events are queued as (severity, text) for STATUSTEXT and the trace.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from . import flight_tasks
from .flight_tasks import VelocityCommand
from .kinematics import Kinematics
from .params import (
    OBL_ACTIONS, OBL_ALTITUDE, OBL_DISARM, OBL_HOLD, OBL_LAND, OBL_MANUAL, OBL_POSITION, OBL_RETURN, OBL_TERMINATE, ParamTable,
)  # fmt: skip
from .px4 import ALTCTL, HOLD, LAND, MANUAL, OFFBOARD, POSCTL, RETURN, TAKEOFF, Px4Mode
from .setpoints import STICK_TIMEOUT_S, OffboardSetpoint, Sticks

log = logging.getLogger(__name__)

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
DENIED = mavlink.MAV_RESULT_DENIED
TEMPORARILY_REJECTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED

# OFFBOARD is entered only with a setpoint at most this old (PX4 wants the stream running first).
OFFBOARD_ENTRY_MAX_SETPOINT_AGE_S = 0.5
# DO_SET_MODE can select these; PX4's manual modes need attitude sticks this vehicle does not fly.
SELECTABLE_MODES = (HOLD, TAKEOFF, LAND, OFFBOARD, POSCTL)
# Return mode: fly home at the current height, then land, once within this horizontal distance (m).
RETURN_ACCEPTANCE_M = 0.3
# PX4 v1.16 SITL's start-up as recorded on its GCS link (tests/sim/follower/fixtures/
# px4_v1_16_startup.json): HEARTBEAT system_status UNINIT until 4.25 s after start, STANDBY after;
# SYS_STATUS's pre-arm bit healthy from 5.27 s, and never set as present or enabled.
PX4_STANDBY_AFTER_S = 4.25
PX4_PREARM_AFTER_S = 5.27
# The offboard-loss failsafe's mode per COM_OBL_RC_ACT (Terminate and Disarm stop the motors instead).
_OBL_MODES = {OBL_POSITION: POSCTL, OBL_ALTITUDE: ALTCTL, OBL_MANUAL: MANUAL, OBL_RETURN: RETURN, OBL_LAND: LAND,
              OBL_HOLD: HOLD}  # fmt: skip
# Modes flown with RC sticks: without RC input PX4 cannot run them and its failsafe flight task
# descends and lands where the vehicle is (the mode still reads as selected).
_STICK_MODES = (POSCTL, ALTCTL, MANUAL)


@dataclass(frozen=True)
class Event:
    """Something a pilot should read: MAV_SEVERITY and a STATUSTEXT-sized text."""

    t_s: float
    severity: int
    text: str


class Commander:
    """Arming state, flight mode and the targets of the current mode (see the module doc)."""

    def __init__(
        self,
        params: ParamTable,
        home_enu_m: np.ndarray,
        kin: Kinematics,
        t_s: float,
        offboard_allowed: Callable[[float], bool] | None = None,
        boot_time_scale: float = 0.0,
    ) -> None:
        """``offboard_allowed(t_s)``, when given, is asked before OFFBOARD is entered (False:
        DENIED, as PX4 refuses a mode that is not available; the fault injection uses it).
        ``boot_time_scale``: PX4's start-up (booting, then pre-arm checks passing) replayed at this
        fraction of its recorded times (1: as PX4; 0: ready at once)."""
        if not 0.0 <= boot_time_scale <= 1.0:
            raise ValueError(f"boot_time_scale {boot_time_scale} must be in [0, 1]")
        self._params = params
        self._offboard_allowed = offboard_allowed
        self._home_enu_m = np.asarray(home_enu_m, dtype=np.float64)
        self.armed = False
        self.crashed = False
        # Boot in Hold, a mode that needs no pilot input.  Which mode a real PX4 without RC shows
        # before take-off depends on its version and parameters; nothing in the runtime relies on it.
        self.mode = HOLD
        self.mode_log: list[tuple[float, str]] = [(t_s, HOLD.name)]
        self._events: list[Event] = []
        self._setpoint: OffboardSetpoint | None = None
        self._sticks: Sticks | None = None
        # Take-off and landing fly to _target_enu_m; Hold, Position mode and an offboard without
        # setpoints hold through _brake (which brakes to a stop first when engaged in flight).
        self._target_enu_m = kin.pos_enu_m.copy()
        self._brake = flight_tasks.Brake(kin.pos_enu_m)
        self._target_yaw_enu_rad = kin.yaw_enu_rad
        self._t_armed_s = t_s
        self._airborne_since_arm = False
        self._on_ground = kin.on_ground
        self._t_ground_s = t_s
        # A stick mode engaged by the failsafe without RC input: descend and land where we are.
        self._descend_without_rc = False
        self._t_standby_s = t_s + boot_time_scale * PX4_STANDBY_AFTER_S
        self._t_prearm_s = t_s + boot_time_scale * PX4_PREARM_AFTER_S
        self.booted = boot_time_scale == 0.0  # HEARTBEAT STANDBY (not UNINIT)
        self._prearm_ok = boot_time_scale == 0.0

    # ---- state the telemetry reports ------------------------------------------------------

    @property
    def landed_state(self) -> int:
        """MAV_LANDED_STATE as EXTENDED_SYS_STATE reports it.  A crashed vehicle is down (MAVLink
        has no "crashed" state), so a client waiting for "disarmed and not in air" is released."""
        if self._on_ground or self.crashed:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.armed and self.mode == TAKEOFF:
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if self.armed and self.mode == LAND:
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    @property
    def armable(self) -> bool:
        """Pre-arm checks pass (SYS_STATUS's pre-arm health bit): booted, on the ground, not crashed."""
        return self._prearm_ok and self._on_ground and not self.crashed

    def drain_events(self) -> list[Event]:
        """Events since the last call, oldest first."""
        events, self._events = self._events, []
        return events

    # ---- commands -------------------------------------------------------------------------

    def arm(self, t_s: float, kin: Kinematics) -> int:
        """Arm if landed, not crashed, and (in OFFBOARD) with setpoints streaming."""
        if self.armed:
            return ACCEPTED
        if self.crashed:
            return self._refuse(t_s, DENIED, "Arming denied: vehicle crashed")
        if not self._prearm_ok:
            return self._refuse(t_s, DENIED, "Arming denied: system not ready (pre-arm checks)")
        if not kin.on_ground:
            return self._refuse(t_s, DENIED, "Arming denied: not landed")
        if self.mode == OFFBOARD and not self._setpoint_fresh(t_s, OFFBOARD_ENTRY_MAX_SETPOINT_AGE_S):
            return self._refuse(t_s, DENIED, "Arming denied: no offboard setpoints")
        self.armed = True
        self._t_armed_s = t_s
        self._airborne_since_arm = False
        self._event(t_s, mavlink.MAV_SEVERITY_INFO, "Armed by external command")
        return ACCEPTED

    def disarm(self, t_s: float, kin: Kinematics, force: bool) -> int:
        """Disarm on the ground; in the air only when forced (the motors stop, it falls)."""
        if not self.armed:
            return ACCEPTED
        if not kin.on_ground and not force:
            return self._refuse(t_s, DENIED, "Disarming denied: not landed")
        self._disarm(t_s, "Disarmed by external command" + (" (forced in air)" if not kin.on_ground else ""))
        return ACCEPTED

    def takeoff(self, t_s: float, kin: Kinematics, alt_above_home_m: float | None) -> int:
        """AUTO.TAKEOFF to alt_above_home_m (MIS_TAKEOFF_ALT when None), then Hold there."""
        if self.crashed:
            return self._refuse(t_s, DENIED, "Takeoff denied: vehicle crashed")
        if not self.armed:
            return self._refuse(t_s, DENIED, "Takeoff denied: disarmed")
        alt_m = self._params["MIS_TAKEOFF_ALT"] if alt_above_home_m is None else alt_above_home_m
        target = kin.pos_enu_m.copy()
        target[2] = self._home_enu_m[2] + alt_m
        self._switch(t_s, TAKEOFF, kin)
        self._target_enu_m = target
        log.info("take-off to %.2f m above home (z = %.2f m ENU)", alt_m, target[2])
        return ACCEPTED

    def land(self, t_s: float, kin: Kinematics) -> int:
        """AUTO.LAND: descend at MPC_LAND_SPEED where we are; auto-disarm after touch-down."""
        if self.crashed:
            return self._refuse(t_s, DENIED, "Land denied: vehicle crashed")
        self._switch(t_s, LAND, kin)
        return ACCEPTED

    def set_mode(self, t_s: float, kin: Kinematics, mode: Px4Mode) -> int:
        """DO_SET_MODE with PX4's acceptance rules for the modes this vehicle flies."""
        if mode == self.mode:
            return ACCEPTED
        if mode == TAKEOFF:
            return self.takeoff(t_s, kin, None)
        if mode == LAND:
            return self.land(t_s, kin)
        if mode not in SELECTABLE_MODES:
            return self._refuse(t_s, DENIED, f"Mode {mode.name} not available in SITL")
        if mode == OFFBOARD:
            if self._offboard_allowed is not None and not self._offboard_allowed(t_s):
                return self._refuse(t_s, DENIED, "Offboard denied: mode not available")
            if not self.armed:
                return self._refuse(t_s, DENIED, "Offboard denied: disarmed")
            if not self._setpoint_fresh(t_s, OFFBOARD_ENTRY_MAX_SETPOINT_AGE_S):
                return self._refuse(t_s, TEMPORARILY_REJECTED, "Offboard denied: no setpoints")
        self._switch(t_s, mode, kin)
        return ACCEPTED

    def rc_mode_switch(self, t_s: float, kin: Kinematics, mode: Px4Mode) -> int:
        """The pilot flips the RC mode switch: the mode changes as by DO_SET_MODE, and PX4 tells
        the companion computer only through the HEARTBEAT's mode."""
        result = self.set_mode(t_s, kin, mode)
        if result == ACCEPTED:
            self._event(t_s, mavlink.MAV_SEVERITY_INFO, f"Pilot switched to {mode.name} (RC)")
        return result

    def on_setpoint(self, setpoint: OffboardSetpoint) -> None:
        """Latest offboard setpoint (its receipt time feeds the entry check and the failsafe)."""
        self._setpoint = setpoint

    def on_sticks(self, sticks: Sticks) -> None:
        """Latest pilot sticks (position mode)."""
        self._sticks = sticks

    def crash(self, t_s: float, what: str) -> None:
        """A collision: the vehicle stops where it is and disarms for good."""
        if self.crashed:
            return
        self.crashed = True
        self.armed = False
        self._event(t_s, mavlink.MAV_SEVERITY_CRITICAL, f"collision: {what}")

    # ---- per physics step -----------------------------------------------------------------

    def update(self, t_s: float, kin: Kinematics) -> None:
        """Start-up, land detection, auto-disarm, take-off completion and the offboard-loss failsafe."""
        self.booted = self.booted or t_s >= self._t_standby_s
        self._prearm_ok = self._prearm_ok or t_s >= self._t_prearm_s
        if kin.on_ground != self._on_ground:
            self._on_ground = kin.on_ground
            self._t_ground_s = t_s
            if kin.on_ground and self.armed:
                self._event(t_s, mavlink.MAV_SEVERITY_INFO, "Landing detected")
        if not self.armed:
            return
        if not kin.on_ground:
            self._airborne_since_arm = True
        elif self._airborne_since_arm and t_s - self._t_ground_s >= self._params["COM_DISARM_LAND"]:
            self._disarm(t_s, "Disarmed by landing")
            return
        elif not self._airborne_since_arm and t_s - self._t_armed_s >= self._params["COM_DISARM_PRFLT"]:
            self._disarm(t_s, "Disarmed: no takeoff")
            return
        # As PX4: the take-off is complete (-> Hold, which climbs on to the target) within
        # NAV_MC_ALT_RAD (0.8 m) of its height; PX4 v1.16 SIH reported Hold 0.65-0.74 m short.
        if self.mode == TAKEOFF and abs(kin.pos_enu_m[2] - self._target_enu_m[2]) < self._params["NAV_MC_ALT_RAD"]:
            target = self._target_enu_m
            self._switch(t_s, HOLD, kin)
            self._target_enu_m = target
            self._brake = flight_tasks.Brake(target)
            self._event(t_s, mavlink.MAV_SEVERITY_INFO, "Takeoff complete, holding")
        if self.mode == RETURN and self._returned_home(kin):
            self._switch(t_s, LAND, kin)
        if self.mode == OFFBOARD and not self._setpoint_fresh(t_s, self._params["COM_OF_LOSS_T"]):
            self._offboard_lost(t_s, kin)

    def _offboard_lost(self, t_s: float, kin: Kinematics) -> None:
        """PX4's offboard-loss failsafe: the action COM_OBL_RC_ACT selects.  Its default, Position
        mode, needs RC sticks: without them PX4 descends and lands where it is, and so does this
        vehicle — a runtime that leaves offboard by going silent is not saved by a kinder SITL."""
        action = int(self._params["COM_OBL_RC_ACT"])
        name = OBL_ACTIONS[action]
        if action in (OBL_TERMINATE, OBL_DISARM):
            self._event(t_s, mavlink.MAV_SEVERITY_CRITICAL, f"Failsafe activated: offboard lost, {name}")
            self._disarm(t_s, f"Disarmed by failsafe ({name})")
            return
        mode = _OBL_MODES[action]
        self._switch(t_s, mode, kin)
        if mode == RETURN:
            self._target_enu_m = np.array([self._home_enu_m[0], self._home_enu_m[1], kin.pos_enu_m[2]])
        if mode in _STICK_MODES and not self._rc_present(t_s):
            self._descend_without_rc = True
            self._event(t_s, mavlink.MAV_SEVERITY_WARNING, f"Failsafe activated: offboard lost, {name} mode; no RC: landing")
        else:
            self._event(t_s, mavlink.MAV_SEVERITY_WARNING, f"Failsafe activated: offboard lost, {name} mode")

    def velocity_command(self, t_s: float, kin: Kinematics) -> VelocityCommand:
        """What the current mode asks of the velocity controller now."""
        if self.mode == OFFBOARD and self._setpoint is not None:
            return flight_tasks.follow_setpoint(kin, self._setpoint, self._target_yaw_enu_rad)
        if self._descend_without_rc:
            return flight_tasks.descend(kin, self._target_enu_m, self._target_yaw_enu_rad, self._params["MPC_LAND_SPEED"])
        if self.mode == RETURN:
            return flight_tasks.hold_position(kin, self._target_enu_m, self._target_yaw_enu_rad)
        if self.mode == TAKEOFF:
            return flight_tasks.climb_to(kin, self._target_enu_m, self._target_yaw_enu_rad, self._params["MPC_TKO_SPEED"])
        if self.mode == LAND:
            return flight_tasks.descend(kin, self._target_enu_m, self._target_yaw_enu_rad, self._params["MPC_LAND_SPEED"])
        if self.mode == POSCTL and self._sticks is not None and t_s - self._sticks.t_rx_s <= STICK_TIMEOUT_S:
            if not self._sticks.is_centred():
                # Sticks fly the vehicle; centring them brakes and holds wherever it stops.
                self._brake = flight_tasks.Brake.engage(kin)
                self._target_yaw_enu_rad = kin.yaw_enu_rad
                return flight_tasks.fly_sticks(kin, self._sticks)
        return self._brake.command(kin, self._target_yaw_enu_rad)

    # ---- internals ------------------------------------------------------------------------

    def _rc_present(self, t_s: float) -> bool:
        return self._sticks is not None and t_s - self._sticks.t_rx_s <= STICK_TIMEOUT_S

    def _returned_home(self, kin: Kinematics) -> bool:
        return float(np.linalg.norm(kin.pos_enu_m[:2] - self._home_enu_m[:2])) < RETURN_ACCEPTANCE_M

    def _setpoint_fresh(self, t_s: float, max_age_s: float) -> bool:
        return self._setpoint is not None and t_s - self._setpoint.t_rx_s <= max_age_s

    def _switch(self, t_s: float, mode: Px4Mode, kin: Kinematics) -> None:
        self._descend_without_rc = False
        self._brake = flight_tasks.Brake.engage(kin)
        self._target_enu_m = flight_tasks.stopping_point(kin)
        self._target_yaw_enu_rad = kin.yaw_enu_rad
        if mode != self.mode:
            log.info("mode %s -> %s", self.mode.name, mode.name)
            self.mode = mode
            self.mode_log.append((t_s, mode.name))

    def _disarm(self, t_s: float, text: str) -> None:
        self.armed = False
        self._event(t_s, mavlink.MAV_SEVERITY_INFO, text)

    def _refuse(self, t_s: float, result: int, text: str) -> int:
        self._event(t_s, mavlink.MAV_SEVERITY_WARNING, text)
        return result

    def _event(self, t_s: float, severity: int, text: str) -> None:
        log.info("event: %s", text)
        self._events.append(Event(t_s, severity, text))
