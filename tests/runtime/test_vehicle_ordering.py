"""Duplicated or reordered telemetry never moves the vehicle state back in time: the estimate
(ODOMETRY) is ordered by the autopilot's ``time_usec``.  Unit checks on the adapter's rule, then
the real thing: MAVSDK against the SITL vehicle through a link that duplicates and reorders."""

from __future__ import annotations

import asyncio
import socket
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from runtime.config import VehicleConfig
from runtime.vehicle import AUTOPILOT_REBOOT_BACKSTEP_US, Vehicle
from sim.linkfault import TO_RUNTIME, Impairment, UdpLinkProxy
from sim.sitl_session import free_port
from tests.e2e.fly_helpers import Sitl

SAMPLE_S = 3.0  # how long the state is watched (s): ~90 estimates at PX4's 30 Hz


def _odometry(t_us: int, north_m: float) -> SimpleNamespace:
    return SimpleNamespace(
        time_usec=t_us,
        position_body=SimpleNamespace(x_m=north_m, y_m=0.0, z_m=-1.0),
        velocity_body=SimpleNamespace(x_m_s=1.0, y_m_s=0.0, z_m_s=0.0),
        q=SimpleNamespace(w=1.0, x=0.0, y=0.0, z=0.0),
        angular_velocity_body=SimpleNamespace(roll_rad_s=0.0, pitch_rad_s=0.0, yaw_rad_s=0.1),
    )


def test_older_and_duplicate_estimates_are_ignored_a_reboot_is_not():
    vehicle = Vehicle()
    vehicle._fields.update(vehicle._estimate_fields(_odometry(2_000_000, 5.0)))
    assert vehicle._estimate_fields(_odometry(2_000_000, 5.0)) == {}  # duplicate
    assert vehicle._estimate_fields(_odometry(1_900_000, 4.9)) == {}  # overtaken by a later one
    assert vehicle.estimates_out_of_order == 2
    newer = vehicle._estimate_fields(_odometry(2_030_000, 5.03))
    assert newer["t_estimate_us"] == 2_030_000 and newer["pos_enu_m"] == pytest.approx([0.0, 5.03, 1.0])
    assert newer["vel_enu_m_s"] == pytest.approx([0.0, 1.0, 0.0])  # body FRD forward, heading north -> ENU +y
    vehicle._fields.update(newer)
    vehicle._fields["t_estimate_us"] = AUTOPILOT_REBOOT_BACKSTEP_US + 10_000_000
    rebooted = vehicle._estimate_fields(_odometry(40_000, 0.0))  # its clock starts again
    assert rebooted["t_estimate_us"] == 40_000


@pytest.mark.timeout(90)
def test_state_never_goes_back_in_time_through_a_duplicating_reordering_link(tmp_path: Path):
    runtime_port = free_port(socket.SOCK_DGRAM)
    bad = Impairment(direction=TO_RUNTIME, jitter_ms=20.0, reorder_frac=0.3, reorder_ms=60.0, duplicate_frac=0.3)
    with UdpLinkProxy(runtime_port, [bad], seed=5, lifetime_s=60.0) as link:
        sitl = Sitl(tmp_path, link.port)
        try:
            times_us = asyncio.run(asyncio.wait_for(_watch_estimate(runtime_port), 40.0))
        finally:
            sitl.stop()
        overtaken = link.stats.overtaken[TO_RUNTIME]
    assert overtaken > 100 and len(times_us) > 30, (overtaken, len(times_us))
    assert np.all(np.diff(times_us) >= 0), "the state went back in time"


async def _watch_estimate(runtime_port: int) -> list[int]:
    vehicle = Vehicle(VehicleConfig(url=f"udpin://127.0.0.1:{runtime_port}"))
    await vehicle.connect()
    try:
        await vehicle.wait_until(lambda s: s.t_estimate_us > 0, 20.0, "a first estimate")
        times_us = []
        end = time.monotonic() + SAMPLE_S
        while time.monotonic() < end:
            times_us.append(vehicle.state().t_estimate_us)
            await asyncio.sleep(0.005)
        assert vehicle.estimates_out_of_order > 0  # late and duplicate estimates did arrive, and were ignored
        return times_us
    finally:
        await vehicle.close()
