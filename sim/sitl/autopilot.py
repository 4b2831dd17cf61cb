"""PX4 as the companion computer sees it over MAVLink: incoming messages and commands go to the
commander, the parameter table or the stream scheduler; every command gets a COMMAND_ACK;
telemetry streams and STATUSTEXTs go out.

One thread drives it (the vehicle's loop), so there are no locks here.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

from pymavlink.dialects.v20 import common as mavlink

from .commander import ACCEPTED, DENIED, Commander, Event
from .geodetic import GeodeticHome
from .kinematics import Kinematics
from .mavlink_endpoint import COMPONENT_ID, SYSTEM_ID, MavlinkEndpoint
from .params import ParamError, ParamTable
from .px4 import Px4Mode, UnknownModeError
from .setpoints import UnsupportedSetpointError, setpoint_from_position_target, sticks_from_manual_control
from .streams import StreamScheduler
from .telemetry import AutopilotStatus, Telemetry

log = logging.getLogger(__name__)

UNSUPPORTED = mavlink.MAV_RESULT_UNSUPPORTED
FORCE_MAGIC = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2: force (disarm in air)
STATUSTEXT_MAX_CHARS = 50

CommandHandler = Callable[[list[float], Kinematics, float], int]


class BadCommandError(ValueError):
    """A command parameter that is NaN, infinite or out of range."""


def _as_int(value: float, what: str) -> int:
    if not math.isfinite(value):
        raise BadCommandError(f"{what} is {value}")
    return int(value)


class Autopilot:
    """Dispatches MAVLink to the commander; publishes telemetry (see the module doc)."""

    def __init__(
        self,
        endpoint: MavlinkEndpoint,
        commander: Commander,
        params: ParamTable,
        telemetry: Telemetry,
        streams: StreamScheduler,
        geodetic_home: GeodeticHome,
        t_boot_ns: int,
    ) -> None:
        self._endpoint = endpoint
        self._commander = commander
        self._params = params
        self._telemetry = telemetry
        self._streams = streams
        self._geo = geodetic_home
        self._t_boot_ns = t_boot_ns
        self._pending: list[mavlink.MAVLink_message] = []
        self._ignored_types: set[str] = set()
        self._setpoint_errors: set[str] = set()
        self._messages: dict[str, Callable[[mavlink.MAVLink_message, Kinematics, float], None]] = {
            "COMMAND_LONG": self._on_command_long,
            "COMMAND_INT": self._on_command_int,
            "SET_POSITION_TARGET_LOCAL_NED": self._on_position_target,
            "MANUAL_CONTROL": self._on_manual_control,
            "PARAM_REQUEST_LIST": self._on_param_request_list,
            "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_SET": self._on_param_set,
            "TIMESYNC": self._on_timesync,
            "PING": self._on_ping,
            # The companion computer's heartbeat: nothing to do (PX4's data-link-loss failsafe,
            # NAV_DLL_ACT, is off by default).
            "HEARTBEAT": lambda msg, kin, t_s: None,
        }
        self._commands: dict[int, CommandHandler] = {
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm_disarm,
            mavlink.MAV_CMD_NAV_TAKEOFF: self._cmd_takeoff,
            mavlink.MAV_CMD_NAV_LAND: lambda p, kin, t_s: self._commander.land(t_s, kin),
            mavlink.MAV_CMD_DO_SET_MODE: self._cmd_set_mode,
            mavlink.MAV_CMD_REQUEST_MESSAGE: self._cmd_request_message,
            mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._cmd_request_capabilities,
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_message_interval,
        }

    # ---- incoming -------------------------------------------------------------------------

    def handle(self, msg: mavlink.MAVLink_message, kin: Kinematics, t_s: float) -> None:
        """Act on one received message; malformed content is logged and ignored."""
        handler = self._messages.get(msg.get_type())
        if handler is None:
            if msg.get_type() not in self._ignored_types:
                self._ignored_types.add(msg.get_type())
                log.info("ignoring %s messages (not used by this vehicle)", msg.get_type())
            return
        try:
            handler(msg, kin, t_s)
        except (ValueError, OverflowError) as err:
            log.warning("ignored a malformed %s from %d/%d: %s", msg.get_type(), msg.get_srcSystem(), msg.get_srcComponent(), err)

    @staticmethod
    def _for_us(target_system: int, target_component: int | None = None) -> bool:
        return target_system in (0, SYSTEM_ID) and (target_component is None or target_component in (0, COMPONENT_ID))

    def _on_command_long(self, msg: mavlink.MAVLink_message, kin: Kinematics, t_s: float) -> None:
        params = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7]
        self._on_command(msg, params, kin, t_s)

    def _on_command_int(self, msg: mavlink.MAVLink_message, kin: Kinematics, t_s: float) -> None:
        params = [msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z]
        self._on_command(msg, params, kin, t_s)

    def _on_command(self, msg: mavlink.MAVLink_message, params: list[float], kin: Kinematics, t_s: float) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        handler = self._commands.get(msg.command)
        if handler is None:
            log.info("command %d unsupported (ACK UNSUPPORTED)", msg.command)
            result = UNSUPPORTED
        else:
            try:
                result = handler(params, kin, t_s)
            except BadCommandError as err:
                log.warning("command %d denied: %s", msg.command, err)
                result = DENIED
        log.info("command %d %s -> %s", msg.command, [round(p, 3) for p in params[:3]], mavlink.enums["MAV_RESULT"][result].name)
        self._endpoint.send(
            mavlink.MAVLink_command_ack_message(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        )
        # Messages a command asked for go out after its ACK, as PX4 does.
        for reply in self._pending:
            self._endpoint.send(reply)
        self._pending.clear()

    def _cmd_arm_disarm(self, p: list[float], kin: Kinematics, t_s: float) -> int:
        arm = _as_int(p[0], "param1 (arm)")
        force = math.isfinite(p[1]) and int(p[1]) == FORCE_MAGIC
        if arm == 1:
            return self._commander.arm(t_s, kin)
        if arm == 0:
            return self._commander.disarm(t_s, kin, force)
        raise BadCommandError(f"param1 (arm) must be 0 or 1, got {p[0]}")

    def _cmd_takeoff(self, p: list[float], kin: Kinematics, t_s: float) -> int:
        # param7 is the altitude AMSL; MAVSDK sends NaN, meaning "MIS_TAKEOFF_ALT above home".
        alt_above_home_m = p[6] - self._geo.alt_amsl_m if math.isfinite(p[6]) else None
        return self._commander.takeoff(t_s, kin, alt_above_home_m)

    def _cmd_set_mode(self, p: list[float], kin: Kinematics, t_s: float) -> int:
        base_mode = _as_int(p[0], "param1 (base mode)")
        if not base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            raise BadCommandError(f"base mode {base_mode} lacks MAV_MODE_FLAG_CUSTOM_MODE_ENABLED; PX4 needs custom modes")
        try:
            mode = Px4Mode.from_main_sub(_as_int(p[1], "param2 (main mode)"), _as_int(p[2], "param3 (sub mode)"))
        except UnknownModeError as err:
            raise BadCommandError(str(err)) from err
        return self._commander.set_mode(t_s, kin, mode)

    def _cmd_request_message(self, p: list[float], kin: Kinematics, t_s: float) -> int:
        msg_id = _as_int(p[0], "param1 (message id)")
        if not self._telemetry.can_build(msg_id):
            return UNSUPPORTED
        self._pending.append(self._telemetry.build(msg_id, kin, self.status()))
        return ACCEPTED

    def _cmd_request_capabilities(self, p: list[float], kin: Kinematics, t_s: float) -> int:
        self._pending.append(self._telemetry.autopilot_version())
        return ACCEPTED

    def _cmd_set_message_interval(self, p: list[float], kin: Kinematics, t_s: float) -> int:
        msg_id = _as_int(p[0], "param1 (message id)")
        if not math.isfinite(p[1]):
            raise BadCommandError(f"param2 (interval) is {p[1]}")
        return ACCEPTED if self._streams.set_interval(msg_id, p[1], t_s) else DENIED

    def _on_position_target(self, msg: mavlink.MAVLink_message, kin: Kinematics, t_s: float) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        try:
            setpoint = setpoint_from_position_target(
                msg.coordinate_frame, msg.type_mask, (msg.vx, msg.vy, msg.vz), msg.yaw, msg.yaw_rate, kin.yaw_enu_rad, t_s
            )
        except UnsupportedSetpointError as err:
            if str(err) not in self._setpoint_errors:
                self._setpoint_errors.add(str(err))
                log.warning("ignoring setpoints: %s", err)
            return
        self._commander.on_setpoint(setpoint)

    def _on_manual_control(self, msg: mavlink.MAVLink_message, kin: Kinematics, t_s: float) -> None:
        if self._for_us(msg.target):
            self._commander.on_sticks(sticks_from_manual_control(msg.x, msg.y, msg.z, msg.r, t_s))

    # ---- parameters -----------------------------------------------------------------------

    def _param_value(self, name: str) -> mavlink.MAVLink_message:
        param = self._params.find(name, -1)
        return mavlink.MAVLink_param_value_message(
            param.name.encode(), ParamTable.wire_value(param), param.param_type, len(self._params), self._params.index_of(name)
        )

    def _on_param_request_list(self, msg: mavlink.MAVLink_message, kin: Kinematics, t_s: float) -> None:
        if self._for_us(msg.target_system, msg.target_component):
            for param in self._params.all():
                self._endpoint.send(self._param_value(param.name))

    def _on_param_request_read(self, msg: mavlink.MAVLink_message, kin: Kinematics, t_s: float) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        try:
            param = self._params.find(msg.param_id, msg.param_index)
        except ParamError as err:
            log.info("PARAM_REQUEST_READ: %s (no reply, as PX4)", err)
            return
        self._endpoint.send(self._param_value(param.name))

    def _on_param_set(self, msg: mavlink.MAVLink_message, kin: Kinematics, t_s: float) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        try:
            param = self._params.set_from_wire(msg.param_id, msg.param_value, msg.param_type)
        except ParamError as err:
            log.warning("PARAM_SET refused: %s", err)
            return
        self._endpoint.send(self._param_value(param.name))

    # ---- link housekeeping ----------------------------------------------------------------

    def _on_timesync(self, msg: mavlink.MAVLink_message, kin: Kinematics, t_s: float) -> None:
        if msg.tc1 == 0:
            self._endpoint.send(mavlink.MAVLink_timesync_message(kin.t_ns - self._t_boot_ns, msg.ts1))

    def _on_ping(self, msg: mavlink.MAVLink_message, kin: Kinematics, t_s: float) -> None:
        if msg.target_system == 0 and msg.target_component == 0:
            self._endpoint.send(
                mavlink.MAVLink_ping_message(msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent())
            )

    # ---- outgoing -------------------------------------------------------------------------

    def status(self) -> AutopilotStatus:
        c = self._commander
        return AutopilotStatus(c.armed, c.mode, c.landed_state, c.armable, c.crashed, c.booted)

    def publish(self, kin: Kinematics, t_s: float, events: list[Event] | None = None) -> list[Event]:
        """Send the streams due now and a STATUSTEXT per event; return those events.
        ``events`` None: the commander's new events (drained); a second link of the same vehicle
        passes the ones the first link drained, as PX4 sends its STATUSTEXTs on every link."""
        status = self.status()
        for msg_id in self._streams.due(t_s):
            self._endpoint.send(self._telemetry.build(msg_id, kin, status))
        if events is None:
            events = self._commander.drain_events()
        for event in events:
            self._endpoint.send(mavlink.MAVLink_statustext_message(event.severity, event.text[:STATUSTEXT_MAX_CHARS].encode()))
        return events
