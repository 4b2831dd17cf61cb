"""The autopilot link: MAVSDK-Python >= 4.1 (native asyncio API, no mavsdk_server).

Telemetry (PX4 side: NED world, FRD body) arrives as MAVSDK subscriptions and is kept, with
its receive time (``time.monotonic_ns``), in a cache.  The state estimate (position, velocity,
attitude, body rates) comes from one message, ODOMETRY (PX4 streams it at 30 Hz on the onboard
link), ordered by its ``time_usec``: a duplicated or late datagram (a lossy radio, a MAVLink
router) never moves the state back in time, and the four parts are always of one instant.
MAVSDK's position/velocity and angular-rate messages carry no time, so they are not used. :meth:`Vehicle.state` gives a snapshot on
the policy side (local ENU world, FLU body) as a :class:`runtime.state.VehicleState`.  Commands wrap MAVSDK's
Action and Offboard plugins; every await that talks to the autopilot has a timeout and every
failure raises a :class:`VehicleError` naming the command, the cause and what to check.
"""

from __future__ import annotations

import asyncio
import ctypes
import logging
import time
from typing import AsyncIterator, Awaitable, Callable, TypeVar

import numpy as np
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk, MavsdkConnectionError, MavsdkError
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.mission_raw import MissionRawAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync
from mavsdk.asyncio.plugins.offboard import VelocityBodyYawspeed as MavsdkVelocityBodyYawspeed
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from mavsdk.plugins.telemetry.telemetry import Odometry, OdometryCallback

from .config import VehicleConfig
from .programs.mission_goals import RawMissionItem
from .contract import HOVER, VelocityBodyYawspeed
from .contract.frames import ned_to_enu, quat_ned_frd_to_enu_flu
from .service.shutdown import in_daemon_thread, wait_within
from .tracking import VelocityBias, setpoint_with_bias
from .state import (
    MODE_HOLD,
    VehicleCommandError,
    VehicleError,
    VehicleHealth,
    VehicleState,
    VehicleTimeoutError,
    append_status_text,
)

log = logging.getLogger(__name__)

T = TypeVar("T")

# Height tolerance for "takeoff altitude reached" (m): PX4 itself calls a takeoff done within 10%.
TAKEOFF_ALT_TOLERANCE_FRAC = 0.1
# An estimate this far (µs) behind the kept one is not a late datagram (those are late by a link's
# delay, well under a second) but an autopilot that rebooted: its clock starts again from zero.
AUTOPILOT_REBOOT_BACKSTEP_US = 5_000_000

class Vehicle:
    """One autopilot over MAVSDK: telemetry cache and commands with timeouts."""

    def __init__(self, config: VehicleConfig = VehicleConfig()) -> None:
        self.config = config
        self._mavsdk: Mavsdk | None = None
        self._action: ActionAsync | None = None
        self._offboard: OffboardAsync | None = None
        self._telemetry: TelemetryAsync | None = None
        self._mission_raw: MissionRawAsync | None = None
        self._tasks: list[asyncio.Task] = []
        self._fields: dict[str, object] = {}
        self._updated = asyncio.Event()
        self.setpoints_sent = 0
        self.estimates_out_of_order = 0  # ODOMETRY messages not newer than the kept estimate, ignored
        # The estimate's velocity error against its position's rate (None: corrected off, bias 0).
        self.velocity_bias = VelocityBias(config.velocity_bias_window_s) if config.velocity_bias_correction else None

    # ------------------------------------------------------------------ connection

    async def connect(self) -> None:
        """Open the MAVLink connection, wait for the autopilot, start the telemetry subscriptions."""
        url = self.config.url
        self._mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
        try:
            await wait_within(self._mavsdk.add_any_connection(url), self.config.command_timeout_s)
        except MavsdkConnectionError as err:
            raise VehicleError(f"MAVSDK could not open {url!r} ({err}): is the port free and the URL right?") from err
        except asyncio.TimeoutError as err:
            raise VehicleTimeoutError(f"opening {url!r} took over {self.config.command_timeout_s} s") from err
        system = await self._mavsdk.first_autopilot(timeout_s=self.config.connect_timeout_s)
        if system is None:
            raise VehicleTimeoutError(
                f"no autopilot heartbeat on {url!r} within {self.config.connect_timeout_s} s: "
                "is the autopilot (or SITL vehicle) running and sending to this port?"
            )
        self._action = ActionAsync(system)
        self._offboard = OffboardAsync(system)
        self._telemetry = TelemetryAsync(system)
        self._mission_raw = MissionRawAsync(system)
        self._start_subscriptions()
        log.info("connected to the autopilot on %s", url)

    async def close(self) -> None:
        """Stop the telemetry subscriptions and release MAVSDK (stops any setpoint re-sending).

        MAVSDK's C teardown runs in a daemon thread: bounded by :func:`runtime.service.shutdown.close_step`,
        a teardown that never returns cannot keep the process alive after landing."""
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        handles = [h for h in (self._offboard, self._action, self._telemetry, self._mission_raw, self._mavsdk) if h is not None]
        self._offboard = self._action = self._telemetry = self._mission_raw = self._mavsdk = None

        def destroy() -> None:  # plugins before the instance; each destroy() is idempotent and thread-safe
            for handle in handles:
                handle.destroy()

        if handles:
            await in_daemon_thread("mavsdk-destroy", destroy)

    # ------------------------------------------------------------------ telemetry

    def _start_subscriptions(self) -> None:
        tel = self._require(self._telemetry)
        handlers: dict[str, tuple[Callable, Callable[[object], dict]]] = {
            "estimate": (lambda: subscribe_odometry(tel), self._estimate_fields),  # not tel.subscribe_odometry: it leaks
            "mode": (tel.subscribe_flight_mode, lambda m: {"flight_mode": m.name}),
            "armed": (tel.subscribe_armed, lambda a: {"armed": bool(a)}),
            "in_air": (tel.subscribe_in_air, lambda a: {"in_air": bool(a)}),
            "landed": (tel.subscribe_landed_state, lambda s: {"landed_state": s.name}),
            "health": (tel.subscribe_health, _health_fields),
            "home": (tel.subscribe_home, _home_fields),
            "status_text": (tel.subscribe_status_text, self._status_text_fields),
        }
        stamp_key = {"mode": "t_mode_ns", "armed": "t_armed_ns", "health": "t_health_ns"}  # the estimate stamps itself
        for name, (subscribe, convert) in handlers.items():
            task = asyncio.create_task(self._follow(subscribe, convert, stamp_key.get(name)), name=f"telemetry_{name}")
            task.add_done_callback(_log_subscription_end)
            self._tasks.append(task)

    async def _follow(self, subscribe: Callable, convert: Callable[[object], dict], stamp_key: str | None) -> None:
        async for message in subscribe():
            fields = convert(message)
            if not fields:
                continue
            if stamp_key is not None:
                fields[stamp_key] = time.monotonic_ns()
            self._fields.update(fields)
            self._updated.set()
            self._updated = asyncio.Event()

    def _estimate_fields(self, odometry) -> dict:
        """ODOMETRY -> position, velocity, attitude and rates with their receive time, or nothing
        (no update) when it is not newer than the estimate kept: a duplicate, or a datagram
        overtaken by a later one.  A time far behind is a rebooted autopilot: taken as new."""
        t_us = int(odometry.time_usec)
        kept_us = self._fields.get("t_estimate_us", 0)
        if 0 < t_us <= kept_us and kept_us - t_us < AUTOPILOT_REBOOT_BACKSTEP_US:  # type: ignore[operator]
            self.estimates_out_of_order += 1
            return {}
        now = time.monotonic_ns()
        fields = _odometry_fields(odometry)
        if self.velocity_bias is not None:
            bias = self.velocity_bias.update(t_us * 1e-6, fields["pos_enu_m"], fields["vel_enu_m_s"])
            fields["vel_enu_m_s"] = fields["vel_enu_m_s"] - bias
            fields["vel_bias_enu_m_s"] = bias.copy()
        return {**fields, "t_estimate_us": t_us, "t_posvel_ns": now, "t_att_ns": now, "t_angvel_ns": now}

    def _status_text_fields(self, message) -> dict:
        """A STATUSTEXT (MAVSDK ``StatusText``: ``type`` is a StatusTextType named as MAV_SEVERITY)
        appended to the kept ones, and logged at its severity."""
        severity, text = message.type.name, str(message.text)
        log.log(_LOG_LEVEL.get(severity, logging.INFO), "autopilot %s: %s", severity, text)
        kept = self._fields.get("status_texts", ())
        return {"status_texts": append_status_text(kept, time.monotonic_ns(), severity, text)}  # type: ignore[arg-type]

    def state(self) -> VehicleState:
        """The latest telemetry as a :class:`VehicleState` snapshot."""
        return VehicleState(**self._fields)  # type: ignore[arg-type]

    async def wait_until(self, predicate: Callable[[VehicleState], bool], timeout_s: float, what: str) -> VehicleState:
        """Wait until ``predicate(state)`` holds; raise :class:`VehicleTimeoutError` naming ``what``."""

        async def wait() -> VehicleState:
            while True:
                state = self.state()
                if predicate(state):
                    return state
                await self._updated.wait()

        try:
            return await wait_within(wait(), timeout_s)
        except asyncio.TimeoutError as err:
            state = self.state()
            raise VehicleTimeoutError(
                f"{what} not reached within {timeout_s} s (mode {state.flight_mode}, armed {state.armed}, "
                f"landed {state.landed_state}, height above home {state.height_above_home_m:.2f} m, health {state.health})"
            ) from err

    async def wait_ready(self) -> VehicleState:
        """Wait until the autopilot is armable with a local position and a home position."""
        return await self.wait_until(
            lambda s: s.health.armable and s.health.local_position_ok and s.home_enu_m is not None
            and s.t_telemetry_ns > 0,
            self.config.health_timeout_s,
            "health (armable, local position, home)",
        )  # fmt: skip

    # ------------------------------------------------------------------ commands

    async def arm(self) -> None:
        await self._command("arm", self._require(self._action).arm())

    async def disarm(self) -> None:
        await self._command("disarm", self._require(self._action).disarm())

    async def set_takeoff_altitude(self, altitude_m: float) -> None:
        """Set the autopilot's takeoff altitude above home (PX4 parameter MIS_TAKEOFF_ALT), m."""
        await self._command("set takeoff altitude", self._require(self._action).set_takeoff_altitude(float(altitude_m)))

    async def takeoff(self, altitude_m: float | None = None) -> None:
        """Take off to ``altitude_m`` above home (set first), or to the autopilot's takeoff altitude."""
        if altitude_m is not None:
            await self.set_takeoff_altitude(altitude_m)
        await self._command("takeoff", self._require(self._action).takeoff())

    async def wait_takeoff_done(self, altitude_m: float, short_by_m: float | None = None) -> VehicleState:
        """Wait until the mode is Hold in the air with the height above home at most ``short_by_m``
        below ``altitude_m`` (default: 10 % of it)."""
        low = altitude_m - (altitude_m * TAKEOFF_ALT_TOLERANCE_FRAC if short_by_m is None else short_by_m)
        return await self.wait_until(
            lambda s: s.in_air and s.height_above_home_m >= low and s.flight_mode == MODE_HOLD,
            self.config.takeoff_timeout_s,
            f"takeoff to {altitude_m:.2f} m above home (at least {low:.2f} m) and Hold",
        )

    async def hold(self) -> None:
        """Switch to Hold (PX4 Loiter) outside offboard; in offboard use :meth:`stop_offboard`."""
        await self._command("hold", self._require(self._action).hold())

    async def land(self) -> None:
        await self._command("land", self._require(self._action).land())

    async def wait_disarmed(self) -> VehicleState:
        """Wait until the vehicle reports landed and disarmed."""
        return await self.wait_until(
            lambda s: not s.armed and not s.in_air, self.config.land_timeout_s, "landed and disarmed"
        )

    async def start_offboard(self, initial: VelocityBodyYawspeed = HOVER) -> None:
        """Send ``initial`` (a setpoint must exist before offboard starts), then start offboard."""
        await self.set_velocity_body(initial)
        await self._command("offboard start", self._require(self._offboard).start())

    async def stop_offboard(self) -> None:
        """Leave offboard into Hold; MAVSDK stops re-sending the last setpoint."""
        await self._command("offboard stop (Hold)", self._require(self._offboard).stop())

    async def set_velocity_body(self, cmd: VelocityBodyYawspeed) -> None:
        """Send a body-frame velocity setpoint (FRD, m/s; yaw speed deg/s, + = turn right).

        MAVSDK sends it at once and then re-sends the last one at 20 Hz by itself.  The estimate's
        velocity bias (``runtime.tracking.VelocityBias``) is added, so the vehicle flies ``cmd`` where the
        autopilot holds its estimate at the setpoint.
        """
        forward, right, down = cmd.forward_m_s, cmd.right_m_s, cmd.down_m_s
        state = self.state()
        if np.any(state.vel_bias_enu_m_s):
            forward, right, down = setpoint_with_bias(forward, right, down, state.vel_bias_enu_m_s, state.yaw_enu_rad)
        setpoint = MavsdkVelocityBodyYawspeed(forward, right, down, cmd.yawspeed_deg_s)
        offboard = self._require(self._offboard)
        blocking = getattr(offboard, "_plugin", None)  # MAVSDK 4's synchronous plugin behind the asyncio wrapper
        if blocking is None:
            await self._command("set_velocity_body", offboard.set_velocity_body(setpoint))
        else:
            # Called on the event loop, not through the wrapper's hop to the default executor and
            # back: the C call only stores the setpoint and sends it (no answer is awaited, a
            # fraction of a millisecond), while the two thread hops cost more than that and queue
            # behind other work under load (issue 15, the step's "send" stage).
            try:
                blocking.set_velocity_body(setpoint)
            except MavsdkError as err:
                raise self._refused("set_velocity_body", err) from err
        self.setpoints_sent += 1

    # ------------------------------------------------------------------ mission (the ground station's plan)

    async def download_mission(self) -> list[RawMissionItem]:
        """The mission uploaded to the autopilot (QGroundControl's plan), item by item as
        MISSION_ITEM_INT carries it (MAVSDK mission_raw); empty when there is none."""
        items = await self._command("mission download", self._require(self._mission_raw).download_mission())
        return [RawMissionItem(int(i.seq), int(i.frame), int(i.command), float(i.x), float(i.y), float(i.z)) for i in items]

    async def set_current_mission_item(self, seq: int) -> None:
        """Make mission item ``seq`` the current one: the autopilot reports it (MISSION_CURRENT) to
        every ground station, which shows the progress."""
        await self._command(f"set current mission item {seq}", self._require(self._mission_raw).set_current_mission_item(int(seq)))

    async def home_geodetic_deg(self) -> tuple[float, float]:
        """Home (HOME_POSITION) as (latitude, longitude) in degrees: the origin mission waypoints
        are placed from.  :class:`VehicleError` if the autopilot has not reported one."""
        home = await self._command("home position", self._require(self._telemetry).home())
        lat_deg, lon_deg = float(home.latitude_deg), float(home.longitude_deg)
        if not (np.isfinite(lat_deg) and np.isfinite(lon_deg)) or (lat_deg == 0.0 and lon_deg == 0.0):
            raise VehicleError(f"the autopilot reports no geodetic home (latitude {lat_deg}, longitude {lon_deg}): "
                               "mission waypoints cannot be placed; wait for a GPS fix / home position and restart")  # fmt: skip
        return lat_deg, lon_deg

    async def _command(self, what: str, awaitable: Awaitable[T]) -> T:
        try:
            return await wait_within(awaitable, self.config.command_timeout_s)
        except asyncio.TimeoutError as err:
            raise VehicleTimeoutError(
                f"{what}: no answer from the autopilot within {self.config.command_timeout_s} s: is the link up?"
            ) from err
        except MavsdkError as err:
            raise self._refused(what, err) from err

    def _refused(self, what: str, err: MavsdkError) -> VehicleCommandError:
        return VehicleCommandError(f"{what} refused: {err} (mode {self.state().flight_mode}, "
                                   f"armed {self.state().armed}); check the autopilot's messages")  # fmt: skip

    @staticmethod
    def _require(plugin: T | None) -> T:
        if plugin is None:
            raise VehicleError("not connected to an autopilot: call Vehicle.connect() first")
        return plugin


# The autopilot's severities as log levels (its CRITICAL and worse: errors of the flight).
_LOG_LEVEL = {"EMERGENCY": logging.CRITICAL, "ALERT": logging.CRITICAL, "CRITICAL": logging.ERROR,
              "ERROR": logging.ERROR, "WARNING": logging.WARNING, "DEBUG": logging.DEBUG}  # fmt: skip


def _log_subscription_end(task: asyncio.Task) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.error("telemetry subscription %s failed; its values go stale", task.get_name(), exc_info=task.exception())


def _posvel_fields(pv) -> dict:
    pos_ned = np.array([pv.position.north_m, pv.position.east_m, pv.position.down_m])
    vel_ned = np.array([pv.velocity.north_m_s, pv.velocity.east_m_s, pv.velocity.down_m_s])
    return {"pos_enu_m": ned_to_enu(pos_ned), "vel_enu_m_s": ned_to_enu(vel_ned)}


def _attitude_fields(q) -> dict:
    return {"quat_enu_flu": quat_ned_frd_to_enu_flu(np.array([q.w, q.x, q.y, q.z]))}


def _angvel_fields(w) -> dict:
    # FRD body rates (p, q, r) -> FLU (p, -q, -r).
    return {"angvel_body_flu_rad_s": np.array([w.roll_rad_s, -w.pitch_rad_s, -w.yaw_rad_s])}


def _odometry_fields(odometry) -> dict:
    """PX4's ODOMETRY as PX4 v1.16 sends it (MAVSDK reports its frames as UNDEF): pose and
    velocity in local NED (``child_frame_id`` MAV_FRAME_LOCAL_NED: EKF2's velocity frame),
    quaternion FRD -> NED, rates in body FRD.  MAVSDK names the fields ``*_body`` whatever the
    frame; recorded: tests/runtime/fixtures/px4_v1_16_odometry.json."""
    pos = odometry.position_body
    vel = odometry.velocity_body
    return {
        "pos_enu_m": ned_to_enu(np.array([pos.x_m, pos.y_m, pos.z_m])),
        "vel_enu_m_s": ned_to_enu(np.array([vel.x_m_s, vel.y_m_s, vel.z_m_s])),
        **_attitude_fields(odometry.q),
        **_angvel_fields(odometry.angular_velocity_body),
    }


def _health_fields(h) -> dict:
    return {
        "health": VehicleHealth(
            armable=bool(h.is_armable),
            local_position_ok=bool(h.is_local_position_ok),
            global_position_ok=bool(h.is_global_position_ok),
            home_position_ok=bool(h.is_home_position_ok),
            gyro_ok=bool(h.is_gyrometer_calibration_ok),
            accel_ok=bool(h.is_accelerometer_calibration_ok),
            mag_ok=bool(h.is_magnetometer_calibration_ok),
        )
    }


def _home_fields(home) -> dict:
    local_ned = np.array([home.local_north_m, home.local_east_m, home.local_down_m], dtype=np.float64)
    if not np.all(np.isfinite(local_ned)):
        return {}
    return {"home_enu_m": ned_to_enu(local_ned)}


async def subscribe_odometry(telemetry: TelemetryAsync) -> AsyncIterator[Odometry]:
    """ODOMETRY messages as ``TelemetryAsync.subscribe_odometry`` yields them, with their native
    memory released.

    MAVSDK-Python 4.1.0 hands each ODOMETRY over as a C struct whose two covariance members own
    heap arrays (21 floats each, ``new[]`` in the C layer); its wrapper releases them with
    ``mavsdk_telemetry_odometry_destroy``, which in the shipped ``libcmavsdk.so`` is a bare ``ret``:
    ~190 bytes a message stay allocated (+5.6 kB/s at PX4's 30 Hz: the 200-episode soak's whole
    slope, docs/soak.md).  ``mavsdk_telemetry_covariance_destroy`` does free (``delete[]``, then
    nulls the pointer), so it is called on both members: right for this library and for a fixed
    one.  Otherwise the wrapper's own subscription (same C entry points, the trampoline held until
    the C unsubscribe returns); tests/runtime/test_mavsdk_odometry.py counts the heap per message
    on both."""
    plugin = telemetry._plugin  # the synchronous Telemetry the async one wraps
    lib = plugin._lib
    loop = asyncio.get_running_loop()
    queue: asyncio.Queue[Odometry] = asyncio.Queue()

    def on_message(c_data, _user_data) -> None:  # MAVSDK's receive thread
        try:
            message = Odometry.from_c_struct(c_data)
        finally:
            lib.mavsdk_telemetry_covariance_destroy(ctypes.byref(c_data.pose_covariance))
            lib.mavsdk_telemetry_covariance_destroy(ctypes.byref(c_data.velocity_covariance))
        loop.call_soon_threadsafe(queue.put_nowait, message)

    trampoline = OdometryCallback(on_message)
    handle = lib.mavsdk_telemetry_subscribe_odometry(plugin._require_handle(), trampoline, None)
    plugin._subscriptions[handle] = (trampoline, lib.mavsdk_telemetry_unsubscribe_odometry)
    try:
        while True:
            yield await queue.get()
    finally:
        plugin.unsubscribe_odometry(handle)
