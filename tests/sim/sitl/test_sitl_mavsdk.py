"""The SITL vehicle flown by the real client, MAVSDK 4.1's native asyncio API, over loopback:
discovery, health, take-off, offboard body velocities and their signs, Hold, position mode,
landing with auto-disarm."""

from __future__ import annotations

import asyncio
import math
import time

import pytest
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.manual_control import ManualControlAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync, OffboardError, OffboardResult, VelocityBodyYawspeed
from mavsdk.asyncio.plugins.telemetry import FlightMode, LandedState, TelemetryAsync

pytestmark = [pytest.mark.timeout(90), pytest.mark.flight]


async def _wait_for(stream, predicate, timeout_s: float, what: str):
    """First item of an async telemetry stream that satisfies predicate."""

    async def first():
        async for item in stream:
            if predicate(item):
                return item

    try:
        return await asyncio.wait_for(first(), timeout_s)
    except TimeoutError as err:
        raise AssertionError(f"{what} not seen within {timeout_s} s") from err


async def _fly(offboard: OffboardAsync, command: VelocityBodyYawspeed, duration_s: float) -> None:
    """Send the command like a 15 Hz policy loop would (MAVSDK also re-sends it at 20 Hz)."""
    t_end = time.monotonic() + duration_s
    while time.monotonic() < t_end:
        await offboard.set_velocity_body(command)
        await asyncio.sleep(1 / 15)


def _yaw_diff_deg(after: float, before: float) -> float:
    return (after - before + 180.0) % 360.0 - 180.0


async def _mission(sitl) -> dict:
    report: dict = {}
    async with Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{sitl.mavlink_port}")
        system = await sdk.first_autopilot(timeout_s=20.0)
        assert system is not None, "no autopilot discovered"
        telemetry, action, offboard = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system)
        manual = ManualControlAsync(system)

        health = await _wait_for(
            telemetry.subscribe_health(),
            lambda h: h.is_armable and h.is_home_position_ok and h.is_global_position_ok,
            15.0, "armable health",
        )  # fmt: skip
        report["t_armable_s"] = time.monotonic() - sitl.t_launch_s
        assert health.is_local_position_ok and health.is_gyrometer_calibration_ok
        assert health.is_accelerometer_calibration_ok and health.is_magnetometer_calibration_ok
        assert await telemetry.landed_state() == LandedState.ON_GROUND

        # MAVSDK refuses offboard locally before any setpoint.
        with pytest.raises(OffboardError) as refused:
            await offboard.start()
        assert refused.value.result == OffboardResult.NO_SETPOINT_SET

        # MIS_TAKEOFF_ALT defaults to the episode's take-off altitude; a lower one keeps this test short.
        assert await action.get_takeoff_altitude() == pytest.approx(sitl.episode["takeoff_alt_m"], abs=1e-4)
        alt_m = 1.5
        await action.set_takeoff_altitude(alt_m)
        assert await action.get_takeoff_altitude() == pytest.approx(alt_m, abs=1e-4)
        modes: list = []  # every mode reported from before the arm on: TAKEOFF is short

        async def record_modes():
            async for mode in telemetry.subscribe_flight_mode():
                modes.append(mode)

        recorder = asyncio.create_task(record_modes())
        await asyncio.sleep(0.5)
        await action.arm()
        await action.takeoff()
        await _wait_for(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD, 15.0, "Hold after take-off")
        recorder.cancel()
        assert FlightMode.TAKEOFF in modes and modes.index(FlightMode.TAKEOFF) < len(modes) - 1, modes
        # As PX4, the take-off ends within NAV_MC_ALT_RAD (0.8 m) of its height and Hold climbs on to it.
        pv = await telemetry.position_velocity_ned()
        assert alt_m - 0.8 - 0.1 <= -pv.position.down_m <= alt_m + 0.1
        await _wait_for(telemetry.subscribe_position_velocity_ned(), lambda p: -p.position.down_m > alt_m - 0.2, 10.0, "the height in Hold")
        assert await telemetry.in_air()

        await offboard.set_velocity_body(VelocityBodyYawspeed(0.0, 0.0, 0.0, 0.0))
        await offboard.start()
        await _wait_for(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, 3.0, "OFFBOARD mode")

        # Forward: moves along the heading.
        start = (await telemetry.position_velocity_ned()).position
        yaw_rad = math.radians((await telemetry.attitude_euler()).yaw_deg)
        await _fly(offboard, VelocityBodyYawspeed(1.0, 0.0, 0.0, 0.0), 1.5)
        end = (await telemetry.position_velocity_ned()).position
        d_north, d_east = end.north_m - start.north_m, end.east_m - start.east_m
        along = d_north * math.cos(yaw_rad) + d_east * math.sin(yaw_rad)
        across = -d_north * math.sin(yaw_rad) + d_east * math.cos(yaw_rad)
        assert along > 0.6 and abs(across) < 0.2, (along, across)

        # Positive yaw speed turns right: NED yaw increases; negative turns back.
        yaw0 = (await telemetry.attitude_euler()).yaw_deg
        await _fly(offboard, VelocityBodyYawspeed(0.0, 0.0, 0.0, 45.0), 1.5)
        yaw1 = (await telemetry.attitude_euler()).yaw_deg
        rate = await telemetry.attitude_angular_velocity_body()
        assert _yaw_diff_deg(yaw1, yaw0) > 30.0 and rate.yaw_rad_s > 0.3
        await _fly(offboard, VelocityBodyYawspeed(0.0, 0.0, 0.0, -45.0), 1.5)
        yaw2 = (await telemetry.attitude_euler()).yaw_deg
        # Turning back first undoes the right turn's rate: PX4's yaw answers 0.12 s late with a
        # 0.3 s lag and at most 2.6 rad/s^2 (sim.dynamics.PX4_SIH_V1_16), so 1.5 s give ~-22 deg.
        assert _yaw_diff_deg(yaw2, yaw1) < -15.0

        # Positive down velocity descends.
        down0 = (await telemetry.position_velocity_ned()).position.down_m
        await _fly(offboard, VelocityBodyYawspeed(0.0, 0.0, 0.5, 0.0), 1.2)
        pv = await telemetry.position_velocity_ned()
        assert pv.position.down_m - down0 > 0.3 and pv.velocity.down_m_s > 0.2

        await offboard.stop()
        await _wait_for(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD, 3.0, "Hold after offboard.stop")

        # A pilot switching to Position mode with centred sticks: the vehicle holds.
        await manual.set_manual_control_input(0.0, 0.0, 0.5, 0.0)
        await manual.start_position_control()
        await _wait_for(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.POSCTL, 3.0, "POSCTL mode")
        held0 = (await telemetry.position_velocity_ned()).position
        for _ in range(10):
            await manual.set_manual_control_input(0.0, 0.0, 0.5, 0.0)
            await asyncio.sleep(0.1)
        held1 = (await telemetry.position_velocity_ned()).position
        drift = math.dist((held0.north_m, held0.east_m, held0.down_m), (held1.north_m, held1.east_m, held1.down_m))
        assert drift < 0.2

        await action.land()
        await _wait_for(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.LAND, 3.0, "LAND mode")
        await _wait_for(telemetry.subscribe_armed(), lambda armed: not armed, 20.0, "auto-disarm after landing")
        assert await telemetry.landed_state() == LandedState.ON_GROUND
        assert abs((await telemetry.position()).relative_altitude_m) < 0.1
    return report


def test_mavsdk_mission(launch_sitl):
    sitl = launch_sitl(level=0, seed=1)
    report = asyncio.run(_mission(sitl))
    print(f"SITL vehicle: episode written {sitl.t_ready_s - sitl.t_launch_s:.2f} s and MAVSDK reports armable "
          f"{report['t_armable_s']:.2f} s after process start")  # fmt: skip
    assert sitl.stop() == 0, sitl.log_tail()
    modes = [mode for _, mode in sitl.trace()["mode_log"]]
    assert modes == ["HOLD", "TAKEOFF", "HOLD", "OFFBOARD", "HOLD", "POSCTL", "LAND"]
