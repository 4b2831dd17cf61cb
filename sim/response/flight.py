"""Fly the identification sequence on an autopilot through ``runtime.vehicle.Vehicle`` (MAVSDK,
as the runtime flies) and record what it did.

Take-off to ``takeoff_alt_m``, offboard, the sequence at the control rate (deadline-scheduled),
then one of two endings: ``brake`` (the runtime's: zero velocity until the speed is below
0.2 m/s, Hold, Land) or ``land-at-speed`` (what the runtime did before issue 27: 0.5 m/s
forward, then Hold and Land at once), recording until disarmed.  Every telemetry update is
sampled at SAMPLE_HZ: time, local ENU position and velocity, heading, flight mode.
"""

from __future__ import annotations

import asyncio
import logging
import time

import numpy as np

from runtime.config import VehicleConfig
from runtime.contract import CONTROL_PERIOD_S, HOVER, velocity_flu_to_mavsdk
from runtime.state import VehicleState
from runtime.vehicle import Vehicle

from .sequence import command_schedule, identification_sequence

log = logging.getLogger(__name__)

SAMPLE_HZ = 100.0
ENDINGS = ("brake", "land-at-speed")
BRAKE_SPEED_M_S = 0.2
BRAKE_TIMEOUT_S = 6.0
LAND_AT_SPEED_M_S = 0.5
SETTLE_S = 2.0  # in Hold after take-off, before offboard


class _Sampler:
    """Every new estimate (position/velocity receive time changed) as one sample."""

    def __init__(self, vehicle: Vehicle, t0_ns: int) -> None:
        self._vehicle = vehicle
        self._t0_ns = t0_ns
        self.samples: dict[str, list] = {"t_s": [], "pos_enu_m": [], "vel_enu_m_s": [], "yaw_enu_rad": [], "mode": [],
                                         "in_air": []}  # fmt: skip
        self._last_ns = 0

    async def run(self) -> None:
        while True:
            state = self._vehicle.state()
            if state.t_posvel_ns != self._last_ns and state.t_posvel_ns > 0:
                self._last_ns = state.t_posvel_ns
                s = self.samples
                s["t_s"].append(round((state.t_posvel_ns - self._t0_ns) * 1e-9, 4))
                s["pos_enu_m"].append([round(float(v), 4) for v in state.pos_enu_m])
                s["vel_enu_m_s"].append([round(float(v), 4) for v in state.vel_enu_m_s])
                s["yaw_enu_rad"].append(round(state.yaw_enu_rad, 5))
                s["mode"].append(state.flight_mode)
                s["in_air"].append(state.in_air)
            await asyncio.sleep(1.0 / SAMPLE_HZ)


def _speed(state: VehicleState) -> float:
    return float(np.linalg.norm(state.vel_enu_m_s))


async def fly_sequence(url: str, ending: str = "brake", takeoff_alt_m: float = 2.5) -> dict:
    """Fly the sequence on the autopilot at ``url`` (MAVSDK URL); returns the run record."""
    if ending not in ENDINGS:
        raise ValueError(f"ending {ending!r} must be one of {ENDINGS}")
    vehicle = Vehicle(VehicleConfig(url=url, health_timeout_s=60.0, takeoff_timeout_s=60.0, land_timeout_s=90.0))
    t_sched, cmd_v, steps = command_schedule(identification_sequence())
    await vehicle.connect()
    sampler_task = None
    try:
        await vehicle.wait_ready()
        await vehicle.arm()
        await vehicle.takeoff(takeoff_alt_m)
        await vehicle.wait_takeoff_done(takeoff_alt_m)
        await asyncio.sleep(SETTLE_S)
        await vehicle.start_offboard(HOVER)
        await vehicle.wait_until(lambda s: s.flight_mode == "OFFBOARD", 5.0, "offboard mode")
        t0_ns = time.monotonic_ns()
        sampler = _Sampler(vehicle, t0_ns)
        sampler_task = asyncio.create_task(sampler.run())
        sent_t_s = []
        for t_s, command in zip(t_sched, cmd_v):
            delay_s = t_s - (time.monotonic_ns() - t0_ns) * 1e-9
            if delay_s > 0:
                await asyncio.sleep(delay_s)
            sent_t_s.append(round((time.monotonic_ns() - t0_ns) * 1e-9, 4))
            await vehicle.set_velocity_body(velocity_flu_to_mavsdk(np.array([command[0], command[1], command[2], command[3]])))
        end = await _end(vehicle, ending, t0_ns)
        await vehicle.wait_disarmed()
        await asyncio.sleep(0.5)
        return {
            "autopilot_url": url,
            "control_period_s": CONTROL_PERIOD_S,
            "commands": {"t_s": sent_t_s, "command_v": [[round(float(v), 4) for v in c] for c in cmd_v]},
            "steps": steps,
            "samples": sampler.samples,
            "end": end,
        }
    finally:
        if sampler_task is not None:
            sampler_task.cancel()
        await vehicle.close()


async def _end(vehicle: Vehicle, ending: str, t0_ns: int) -> dict:
    """Bring the vehicle down by ``ending``; returns when Land was commanded and at what speed."""
    def now_s() -> float:
        return (time.monotonic_ns() - t0_ns) * 1e-9

    record: dict = {"ending": ending}
    if ending == "land-at-speed":
        forward = velocity_flu_to_mavsdk(np.array([LAND_AT_SPEED_M_S, 0.0, 0.0, 0.0]))
        for _ in range(int(2.0 / CONTROL_PERIOD_S)):
            await vehicle.set_velocity_body(forward)
            await asyncio.sleep(CONTROL_PERIOD_S)
    else:
        await vehicle.set_velocity_body(HOVER)
        record["t_brake_s"] = round(now_s(), 4)
        t_end = time.monotonic() + BRAKE_TIMEOUT_S
        while _speed(vehicle.state()) >= BRAKE_SPEED_M_S and time.monotonic() < t_end:
            await asyncio.sleep(0.02)
    record["t_hold_s"] = round(now_s(), 4)
    record["speed_at_hold_m_s"] = round(_speed(vehicle.state()), 3)
    await vehicle.stop_offboard()
    if ending == "brake":
        await vehicle.wait_until(lambda s: s.flight_mode == "HOLD", 5.0, "Hold")
    record["t_land_s"] = round(now_s(), 4)
    record["speed_at_land_m_s"] = round(_speed(vehicle.state()), 3)
    record["pos_at_land_enu_m"] = [round(float(v), 4) for v in vehicle.state().pos_enu_m]
    await vehicle.land()
    return record

