"""runtime.vehicle against the SITL vehicle (``python -m sim.sitl``) over loopback: one mission,
in order — connect, health, arm, takeoff, offboard, body velocity, the action mapping's signs
(positive yaw action turns left, positive inclination action climbs), the pilot leaving
offboard mid-flight, Hold, land.  One SITL process and one event loop, and one test: each step
needs the vehicle the step before left (xdist's load distribution split them across workers when
they were tests of their own)."""

import asyncio
import json
import socket
import subprocess
import sys
import time

import numpy as np
import onnx
import pytest

from export.goal_seeker import build_goal_seeker
from runtime.camera.sim_source import SimCameraSource
from runtime.config import RecorderConfig, RuntimeConfig, VehicleConfig, WatchdogConfig
from runtime.contract import HOVER, action_to_mavsdk
from runtime.contract.frames import wrap_angle
from runtime.flight import FlightLoop
from runtime.model import PolicyModel
from runtime.state import MODE_HOLD, MODE_OFFBOARD
from runtime.vehicle import Vehicle
from sim.sitl_session import free_port, stop_process

pytestmark = pytest.mark.timeout(120)




class Mission:
    """The SITL process, an event loop kept across the tests, and the connected vehicle."""

    def __init__(self, tmp_path):
        self.mavlink_port, self.camera_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
        episode_path = tmp_path / "episode.json"
        self.log = open(tmp_path / "sitl.log", "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sim.sitl", "--mavlink-port", str(self.mavlink_port),
             "--camera-port", str(self.camera_port), "--level", "0", "--seed", "2",
             "--episode-json", str(episode_path), "--trace", str(tmp_path / "trace.json")],
            stdout=self.log, stderr=subprocess.STDOUT,
        )  # fmt: skip
        deadline = time.monotonic() + 60
        while not episode_path.exists():
            assert self.proc.poll() is None, f"SITL vehicle exited: {(tmp_path / 'sitl.log').read_text()[-2000:]}"
            assert time.monotonic() < deadline, "SITL vehicle not ready in 60 s"
            time.sleep(0.05)
        time.sleep(0.1)
        self.episode = json.loads(episode_path.read_text())
        self.loop = asyncio.new_event_loop()
        self.vehicle = Vehicle(VehicleConfig(url=f"udpin://127.0.0.1:{self.mavlink_port}", command_timeout_s=5.0))

    def run(self, coro, timeout_s: float = 30.0):
        return self.loop.run_until_complete(asyncio.wait_for(coro, timeout_s))

    def close(self):
        try:
            self.run(self.vehicle.close())
            self.loop.close()
        finally:
            stop_process(self.proc, "SITL vehicle", 10.0)
            self.log.close()


@pytest.fixture
def mission(tmp_path):
    m = Mission(tmp_path)
    try:
        yield m
    finally:
        m.close()


async def _hold_command(vehicle: Vehicle, action: np.ndarray, duration_s: float) -> None:
    """Send the runtime's own mapping of ``action`` at 15 Hz for ``duration_s``."""
    cmd = action_to_mavsdk(action)
    t_end = time.monotonic() + duration_s
    while time.monotonic() < t_end:
        await vehicle.set_velocity_body(cmd)
        await asyncio.sleep(1 / 15)


def _connect_and_health(mission):
    mission.run(mission.vehicle.connect())
    state = mission.run(mission.vehicle.wait_ready())
    assert state.health.armable and state.health.local_position_ok
    np.testing.assert_allclose(state.pos_enu_m, state.home_enu_m, atol=0.05)  # landed at home
    assert not state.armed and not state.in_air
    assert abs(state.yaw_enu_rad) < 0.05  # spawned facing +x (east), the goal side of the room
    assert state.t_telemetry_ns > 0 and time.monotonic_ns() - state.t_telemetry_ns < 1e9


def _arm_and_takeoff(mission):
    alt_m = mission.episode["takeoff_alt_m"]
    vehicle = mission.vehicle
    mission.run(vehicle.arm())
    mission.run(vehicle.takeoff(alt_m))  # sets MIS_TAKEOFF_ALT first
    state = mission.run(vehicle.wait_takeoff_done(alt_m), 40.0)
    assert state.armed and state.in_air and state.flight_mode == MODE_HOLD
    assert state.height_above_home_m == pytest.approx(alt_m, abs=0.35)


def _offboard_forward_body_velocity(mission):
    vehicle = mission.vehicle
    mission.run(vehicle.start_offboard(HOVER))
    mission.run(vehicle.wait_until(lambda s: s.flight_mode == MODE_OFFBOARD, 5.0, "offboard"))
    before = vehicle.state()

    async def fly():
        await _hold_command(vehicle, np.array([0.0, 0.0, 0.0]), 1.5)  # 1 m/s forward, level
        return vehicle.state()

    after = mission.run(fly())
    assert after.vel_body_flu_m_s[0] > 0.5 and abs(after.vel_body_flu_m_s[1]) < 0.2
    moved = after.pos_enu_m - before.pos_enu_m
    heading = np.array([np.cos(before.yaw_enu_rad), np.sin(before.yaw_enu_rad)])
    assert moved[:2] @ heading > 0.5
    mission.run(_hold_command(vehicle, np.array([-1.0, 0.0, 0.0]), 1.0))  # speed 0: brake


def _positive_yaw_action_turns_left(mission):
    vehicle = mission.vehicle
    yaw_before = vehicle.state().yaw_enu_rad
    mission.run(_hold_command(vehicle, np.array([-1.0, 0.0, 0.5]), 1.5))  # no speed, a3 = +0.5
    state = vehicle.state()
    turned = float(wrap_angle(state.yaw_enu_rad - yaw_before))
    assert turned > 0.3, f"yaw changed by {turned:.3f} rad; expected a left (ENU +) turn of ~0.8 rad"
    assert state.angvel_body_flu_rad_s[2] > 0.2  # FLU yaw rate positive = turning left
    mission.run(_hold_command(vehicle, np.array([-1.0, 0.0, -0.5]), 1.5))  # turn back toward the room's length


def _positive_inclination_action_climbs(mission):
    vehicle = mission.vehicle
    z_before = vehicle.state().pos_enu_m[2]
    mission.run(_hold_command(vehicle, np.array([-0.5, 1.0, 0.0]), 1.2))  # 0.5 m/s at +45 deg
    state = vehicle.state()
    assert state.pos_enu_m[2] - z_before > 0.2
    assert state.vel_enu_m_s[2] > 0.1
    mission.run(_hold_command(vehicle, np.array([-1.0, 0.0, 0.0]), 1.0))


def _pilot_leaving_offboard_stops_the_loop(mission, tmp_path):
    """Someone else (here: a Hold command, as a GCS or the RC switch would) takes the vehicle out
    of offboard while the loop flies: the loop stops commanding at once and sends nothing more."""
    vehicle = mission.vehicle
    model_path = tmp_path / "goal_seeker.onnx"
    onnx.save(build_goal_seeker(), str(model_path))
    config = RuntimeConfig(watchdog=WatchdogConfig(hold_grace_s=0.3), recorder=RecorderConfig(log_dir=None))
    loop = FlightLoop(config, PolicyModel(model_path), vehicle, SimCameraSource(mission.camera_port))
    goal = vehicle.state().pos_enu_m + np.array([3.0, 0.0, 0.0])

    async def fly_then_take_over():
        await loop.start()
        try:
            await loop.wait_first_frame(5.0)
            fly = asyncio.create_task(loop.fly(goal, 20.0))
            await asyncio.sleep(1.0)
            await vehicle.hold()  # the "pilot"
            result = await fly
            sent_at_end = vehicle.setpoints_sent
            await asyncio.sleep(0.5)
            return result, sent_at_end
        finally:
            await loop.close()

    result, sent_at_end = mission.run(fly_then_take_over())
    assert result.outcome == "aborted" and result.abort_reason == "pilot_left_offboard", result
    (trip,) = result.watchdog_trips
    assert trip["response"] == "stop_commanding" and trip["detect_ms"] < 500
    assert result.steps >= 5
    assert vehicle.setpoints_sent == sent_at_end  # nothing sent after the takeover
    assert vehicle.state().flight_mode == MODE_HOLD


def _land_and_disarm(mission):
    vehicle = mission.vehicle
    mission.run(vehicle.land())
    state = mission.run(vehicle.wait_disarmed(), 60.0)
    assert not state.armed and not state.in_air
    assert state.height_above_home_m < 0.2


@pytest.mark.timeout(240)
def test_one_mission_in_order(mission, tmp_path):
    _connect_and_health(mission)
    _arm_and_takeoff(mission)
    _offboard_forward_body_velocity(mission)
    _positive_yaw_action_turns_left(mission)
    _positive_inclination_action_climbs(mission)
    _pilot_leaving_offboard_stops_the_loop(mission, tmp_path)
    _land_and_disarm(mission)
