"""The runtime reads PX4's ODOMETRY in the frames PX4 v1.16 really sends (issue 27).

``fixtures/px4_v1_16_odometry.json`` pairs each ODOMETRY that PX4 v1.16.0 SITL sent while it
flew the identification sequence (yawing round through every heading) with the LOCAL_POSITION_NED
of the same instant (``scripts/px4-record-odometry.py``).  ODOMETRY's velocity is local NED
(``child_frame_id`` 1), not body FRD: read as body FRD it points backwards once the vehicle has
turned round, which is what the runtime did before."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from runtime.contract.frames import euler_from_quat, ned_to_enu, quat_ned_frd_to_enu_flu
from runtime.vehicle import _odometry_fields

FIXTURE = Path(__file__).parent / "fixtures" / "px4_v1_16_odometry.json"


def _as_mavsdk(o: dict) -> SimpleNamespace:
    """The recorded ODOMETRY as MAVSDK-Python hands it over (its field names, its units)."""
    w, x, y, z = o["q"]
    return SimpleNamespace(
        position_body=SimpleNamespace(x_m=o["x"], y_m=o["y"], z_m=o["z"]),
        velocity_body=SimpleNamespace(x_m_s=o["vx"], y_m_s=o["vy"], z_m_s=o["vz"]),
        q=SimpleNamespace(w=w, x=x, y=y, z=z),
        angular_velocity_body=SimpleNamespace(roll_rad_s=0.0, pitch_rad_s=0.0, yaw_rad_s=0.0),
    )


def test_the_recording_covers_every_heading_and_says_local_ned():
    pairs = json.loads(FIXTURE.read_text())["pairs"]
    yaws = [euler_from_quat(quat_ned_frd_to_enu_flu(np.array(p["odometry"]["q"])))[2] for p in pairs]
    assert max(yaws) - min(yaws) > 3.0  # turned round: a body-frame reading would show
    assert {p["odometry"]["child_frame_id"] for p in pairs} == {1}  # MAV_FRAME_LOCAL_NED


def test_odometry_velocity_matches_local_position_ned_at_every_heading():
    pairs = json.loads(FIXTURE.read_text())["pairs"]
    moving = [p for p in pairs if np.hypot(p["local_position_ned"]["vx"], p["local_position_ned"]["vy"]) > 0.3]
    assert len(moving) >= 10
    for p in moving:
        local = p["local_position_ned"]
        fields = _odometry_fields(_as_mavsdk(p["odometry"]))
        assert fields["vel_enu_m_s"] == pytest.approx(ned_to_enu(np.array([local["vx"], local["vy"], local["vz"]])), abs=0.02)
