"""The flight loop against an in-process kinematic vehicle and camera (no MAVLink, no SITL)."""

import asyncio
import gc
import time

import numpy as np
import pytest

from runtime.camera import Frame
from runtime.config import RecorderConfig, RuntimeConfig, WatchdogConfig
from runtime.contract import HOVER, CONTROL_PERIOD_S, mavsdk_to_velocity_flu
from runtime.contract.frames import quat_from_euler, quat_rotate
from runtime.flight import FlightLoop
from runtime.model import PolicyModel
from runtime.log.recorder import Recorder
from runtime.state import VehicleHealth, VehicleState
from tests.runtime.onnx_models import save, step_model

# Real-time episodes (the loop's 15 Hz clock and its deadlines): with the SITL flights, never beside
# the computing tests (`make test`), whose load once stretched a step past its deadline here.
pytestmark = pytest.mark.flight

HOME = np.array([0.0, 0.0, 0.0])
START = np.array([1.0, 1.0, 1.5])


class KinematicVehicle:
    """Integrates body velocity commands like a perfect autopilot; mode OFFBOARD until Hold."""

    def __init__(self):
        self.pos = START.copy()
        self.yaw = 0.0
        self.cmd_flu = np.zeros(4)
        self.mode = "OFFBOARD"
        self.t_mode_ns = time.monotonic_ns()
        self.setpoints: list = []
        self.holds = 0
        self._task = None

    async def start(self):
        self._task = asyncio.create_task(self._integrate())

    async def _integrate(self):
        dt = 0.01
        while True:
            if self.mode == "OFFBOARD":
                q = quat_from_euler(0.0, 0.0, self.yaw)
                self.pos = self.pos + quat_rotate(q, self.cmd_flu[:3]) * dt
                self.yaw += self.cmd_flu[3] * dt
            await asyncio.sleep(dt)

    def state(self) -> VehicleState:
        now = time.monotonic_ns()
        q = quat_from_euler(0.0, 0.0, self.yaw)
        return VehicleState(
            pos_enu_m=self.pos.copy(), vel_enu_m_s=quat_rotate(q, self.cmd_flu[:3]), t_posvel_ns=now,
            quat_enu_flu=q, t_att_ns=now, angvel_body_flu_rad_s=np.array([0, 0, self.cmd_flu[3]]), t_angvel_ns=now,
            flight_mode=self.mode, t_mode_ns=self.t_mode_ns, armed=True, in_air=True,
            health=VehicleHealth(armable=True, local_position_ok=True), home_enu_m=HOME,
        )  # fmt: skip

    async def set_velocity_body(self, cmd) -> None:
        self.setpoints.append(cmd)
        self.cmd_flu = mavsdk_to_velocity_flu(cmd)

    async def stop_offboard(self) -> None:
        self.holds += 1
        self.cmd_flu = np.zeros(4)
        self.mode = "HOLD"
        self.t_mode_ns = time.monotonic_ns()

    def pilot_switches_to(self, mode: str):
        self.mode = mode
        self.t_mode_ns = time.monotonic_ns()
        self.cmd_flu = np.zeros(4)


class FakeCamera:
    """15 Hz frames until ``stop_after_s``."""

    def __init__(self, stop_after_s: float | None = None):
        self.stop_after_s = stop_after_s

    async def start(self):
        pass

    async def frames(self):
        t0 = time.monotonic()
        seq = 0
        while self.stop_after_s is None or time.monotonic() - t0 < self.stop_after_s:
            seq += 1
            depth = np.full((120, 212), 3.0, np.float32)
            yield Frame(time.monotonic_ns(), depth, np.full((120, 212), 128, np.uint8), seq)
            await asyncio.sleep(CONTROL_PERIOD_S)
        await asyncio.sleep(3600)

    async def close(self):
        pass


def _config() -> RuntimeConfig:
    return RuntimeConfig(watchdog=WatchdogConfig(hold_grace_s=0.3), recorder=RecorderConfig(flush_period_s=0.2))


async def _fly(model_path, goal, timeout_s, camera=None, during=None, recorder=None):
    vehicle = KinematicVehicle()
    await vehicle.start()
    loop = FlightLoop(_config(), PolicyModel(model_path), vehicle, camera or FakeCamera(), recorder)
    await loop.start()
    try:
        await loop.wait_first_frame(2.0)
        fly = asyncio.create_task(loop.fly(goal, timeout_s))
        if during is not None:
            await during(vehicle)
        result = await fly
    finally:
        await loop.close()
        vehicle._task.cancel()
    return result, vehicle


def test_reaches_goal_then_hover_and_hold(goal_seeker, tmp_path):
    goal = START + np.array([1.2, 1.2, 0.3])  # ahead-left and above: it has to turn left and climb
    recorder = Recorder(tmp_path / "f.mcap", RecorderConfig(flush_period_s=0.2))
    gc.unfreeze()
    frozen_in_flight = []

    async def in_flight(vehicle):
        await asyncio.sleep(0.5)
        frozen_in_flight.append(gc.get_freeze_count())

    result, vehicle = asyncio.run(_fly(goal_seeker, goal, 20.0, during=in_flight, recorder=recorder))
    recorder.close()
    # What existed before the episode was kept out of the collector's reach while it flew, and
    # handed back after (or what was alive then and garbage later would never be collected).
    assert frozen_in_flight[0] > 0 and gc.get_freeze_count() == 0
    assert result.outcome == "success", result
    assert result.final_distance_m < 1.0 and result.watchdog_trips == []
    assert result.steps > 5 and result.step_ms["p50"] is not None
    assert set(result.stage_ms) == {"delivery", "pickup", "frame_age_at_step", "executor_in", "preprocess", "observation",
                                    "inference", "executor_out", "checks", "send", "command", "step", "grab_to_command",
                                    "frame_age"}  # fmt: skip
    assert vehicle.yaw > 0.1  # turned left toward the goal
    assert vehicle.setpoints[-1] == HOVER and vehicle.holds == 1
    assert recorder.stats.written > 0 and recorder.stats.dropped == 0


def test_camera_stops_trips_and_holds(goal_seeker):
    goal = START + np.array([15.0, 0.0, 0.0])  # inside the 20 m geofence, never reached
    result, vehicle = asyncio.run(_fly(goal_seeker, goal, 20.0, camera=FakeCamera(stop_after_s=0.6)))
    assert result.outcome == "aborted" and result.abort_reason == "stale_frame"
    (trip,) = result.watchdog_trips
    assert trip["cause"] == "stale_frame" and trip["response"] == "hover_then_hold"
    assert trip["hold_t_s"] == pytest.approx(trip["t_s"] + 0.3, abs=0.1)
    assert vehicle.setpoints[-1] == HOVER and vehicle.holds == 1


def test_nan_model_trips_before_any_policy_command(tmp_path):
    path = save(step_model(action_offset=float("nan")), tmp_path / "nan.onnx")
    result, vehicle = asyncio.run(_fly(path, START + np.array([5.0, 0, 0]), 10.0))
    assert result.outcome == "aborted" and result.watchdog_trips[0]["cause"] == "bad_action"
    # The NaN never reached the vehicle: only the hover and the brake's setpoints (the vehicle is
    # still, so they are zero too), then Hold.
    assert vehicle.setpoints and all(np.allclose(mavsdk_to_velocity_flu(sp), 0.0) for sp in vehicle.setpoints)
    assert vehicle.holds == 1


def test_pilot_takeover_stops_commanding(goal_seeker):
    async def take_over(vehicle):
        await asyncio.sleep(0.5)
        vehicle.pilot_switches_to("POSCTL")

    goal = START + np.array([15.0, 0.0, 0.0])  # inside the 20 m geofence, never reached
    result, vehicle = asyncio.run(_fly(goal_seeker, goal, 20.0, during=take_over))
    assert result.outcome == "aborted" and result.abort_reason == "pilot_left_offboard"
    assert result.watchdog_trips[0]["response"] == "stop_commanding"
    n = len(vehicle.setpoints)
    assert n > 2 and vehicle.holds == 0 and vehicle.mode == "POSCTL"
    assert all(sp != HOVER for sp in vehicle.setpoints)  # no hover, no Hold: the pilot has it


def test_timeout_hovers_then_holds(goal_seeker):
    result, vehicle = asyncio.run(_fly(goal_seeker, START + np.array([15.0, 0, 0]), 0.8))
    assert result.outcome == "timeout" and result.watchdog_trips == []
    assert result.time_s == pytest.approx(0.8, abs=0.2)
    assert vehicle.setpoints[-1] == HOVER and vehicle.holds == 1


class GarbageCamera(FakeCamera):
    """Good frames for ``good_s``, then garbage: negative depth, another resolution, in turn."""

    def __init__(self, good_s: float):
        super().__init__()
        self.good_s = good_s

    async def frames(self):
        t0 = time.monotonic()
        seq = 0
        while True:
            seq += 1
            if time.monotonic() - t0 < self.good_s:
                depth = np.full((120, 212), 3.0, np.float32)
            else:
                depth = np.full((120, 212), -1.0, np.float32) if seq % 2 else np.full((60, 70), 3.0, np.float32)
            yield Frame(time.monotonic_ns(), depth, np.full(depth.shape, 128, np.uint8), seq)
            await asyncio.sleep(CONTROL_PERIOD_S)


def test_garbage_frames_are_counted_never_flown_on_and_trip(goal_seeker):
    goal = START + np.array([15.0, 0.0, 0.0])  # inside the 20 m geofence, never reached
    result, vehicle = asyncio.run(_fly(goal_seeker, goal, 20.0, camera=GarbageCamera(good_s=0.6)))
    assert result.outcome == "aborted" and result.abort_reason == "bad_frames"
    (trip,) = result.watchdog_trips
    assert "frames rejected since" in trip["detail"] and trip["response"] == "hover_then_hold"
    assert result.frames_rejected >= 3 and result.bad_frames == 0
    assert vehicle.setpoints[-1] == HOVER and vehicle.holds == 1
