"""The identification recovers a known response: a synthetic run of the sequence through a
first-order-plus-dead-time vehicle with a gain deficit (PX4-like numbers) gives back its delay,
time constant and gains, and a zero tracking error only for a perfect vehicle."""

from __future__ import annotations

import numpy as np
import pytest

from runtime.contract import CONTROL_PERIOD_S
from runtime.contract.frames import vehicle_to_world_enu
from sim.response.identify import identify
from sim.response.sequence import command_schedule, identification_sequence

SAMPLE_DT_S = 0.02


def _synthetic_run(delay_s: float, tau_s: float, gain: np.ndarray) -> dict:
    t_cmd, cmd_v, steps = command_schedule(identification_sequence())
    t_end = t_cmd[-1] + 1.0
    n = int(t_end / SAMPLE_DT_S)
    response, yaw, pos = np.zeros(4), 1.57, np.zeros(3)
    samples = {"t_s": [], "pos_enu_m": [], "vel_enu_m_s": [], "yaw_enu_rad": [], "mode": [], "in_air": []}
    for i in range(n):
        t = i * SAMPLE_DT_S
        k = np.searchsorted(t_cmd, t - delay_s, side="right") - 1
        target = gain * cmd_v[k] if k >= 0 else np.zeros(4)
        response = response + (target - response) * (1.0 - np.exp(-SAMPLE_DT_S / tau_s))
        yaw += response[3] * SAMPLE_DT_S
        vel_enu = vehicle_to_world_enu(response[:3], yaw)
        pos = pos + vel_enu * SAMPLE_DT_S
        samples["t_s"].append(t)
        samples["pos_enu_m"].append(pos.tolist())
        samples["vel_enu_m_s"].append(vel_enu.tolist())
        samples["yaw_enu_rad"].append(float(np.arctan2(np.sin(yaw), np.cos(yaw))))
        samples["mode"].append("OFFBOARD")
        samples["in_air"].append(True)
    return {"control_period_s": CONTROL_PERIOD_S, "commands": {"t_s": t_cmd.tolist(), "command_v": cmd_v.tolist()},
            "steps": steps, "samples": samples, "end": None}  # fmt: skip


def test_a_known_response_is_recovered():
    gain = np.array([0.77, 0.75, 0.98, 0.93])
    found = identify(_synthetic_run(delay_s=0.15, tau_s=0.35, gain=gain))
    for k, axis in enumerate(("forward", "left", "up", "yaw_rate")):
        a = found["axes"][axis]
        # 5 % of a first-order rise comes 0.05 tau after the dead time; sampling adds up to a step.
        assert a["delay_s"] == pytest.approx(0.15 + 0.018, abs=0.04)
        assert a["tau_rise_s"] == pytest.approx(0.35 * (1.0 - 0.051), abs=0.05)
        for value, g in a["gain_at"].items():
            assert g == pytest.approx(gain[k], abs=0.02), (axis, value)
    # Read one control period after each command, the lag costs more than the gain deficit alone.
    assert 0.5 < found["tracking_error_m_s"]["forward_ratio"] < 0.77
    assert found["height_drift_m_s"]["mean"] == pytest.approx(0.0, abs=0.01)


def test_a_perfect_vehicle_tracks_with_no_error():
    found = identify(_synthetic_run(delay_s=0.0, tau_s=1e-3, gain=np.ones(4)))
    assert found["tracking_error_m_s"]["p50"] < 0.01
    assert found["tracking_error_m_s"]["forward_ratio"] >= 0.98
