"""Tracking error: commanded (vehicle frame) vs achieved (ground truth) one control period later."""

import math

import numpy as np
import pytest

from sim.tracking import tracking_error


def _trace(t, vel_enu, yaw):
    return {"t_s": list(t), "vel_enu_m_s": [list(v) for v in vel_enu], "yaw_enu_rad": list(yaw)}


def test_perfect_tracking_in_a_turned_vehicle_frame_is_zero():
    t = np.arange(0.0, 5.0, 0.02)
    yaw = np.full_like(t, math.pi / 2)  # facing north: body forward = world +y
    vel = np.stack([np.zeros_like(t), np.full_like(t, 1.5), np.zeros_like(t)], axis=-1)
    t_cmd = np.arange(0.5, 4.0, 1 / 15)
    cmd = np.tile([1.5, 0.0, 0.0], (len(t_cmd), 1))
    result = tracking_error(t_cmd, cmd, _trace(t, vel, yaw))
    assert result["p50"] == result["p99"] == 0.0 and result["n"] == len(t_cmd)
    assert result["forward_ratio"] == pytest.approx(1.0)


def test_a_slow_vehicle_shows_its_shortfall():
    # PX4-like: 2.0 m/s commanded levels at 1.6 m/s (MAVLINK-NOTES.md).
    t = np.arange(0.0, 5.0, 0.02)
    vel = np.tile([1.6, 0.0, 0.3], (len(t), 1))
    t_cmd = np.arange(0.5, 4.0, 1 / 15)
    result = tracking_error(t_cmd, np.tile([2.0, 0.0, 0.0], (len(t_cmd), 1)), _trace(t, vel, np.zeros_like(t)))
    assert result["p50"] == pytest.approx(0.5, abs=1e-6)
    assert result["forward_ratio"] == pytest.approx(0.8)


def test_commands_outside_the_trace_are_not_compared_and_nothing_gives_none():
    t = np.arange(0.0, 1.0, 0.02)
    trace = _trace(t, np.zeros((len(t), 3)), np.zeros_like(t))
    result = tracking_error(np.array([0.5, 3.0]), np.zeros((2, 3)), trace)
    assert result["n"] == 1
    assert tracking_error(np.array([]), np.zeros((0, 3)), trace) is None
    assert tracking_error(np.array([0.5]), np.zeros((1, 3)), {"t_s": [], "vel_enu_m_s": []}) is None
