"""sim.response.replay on recorded flights written the way a `cmnav sitl --autopilot` run writes
them (the runtime's Recorder: estimate and commands; the follower's trace.json: the truth): an
autopilot that holds its *estimate* at the setpoint, flown offline on PX4_SIH_V1_16 with a known
velocity and position error of the estimate.  The replay must find the error and say that the
model predicts the estimate, not the truth."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from runtime.contract import VelocityBodyYawspeed
from runtime.contract.frames import vehicle_to_world_enu
from runtime.log.recorder import Recorder, RecorderConfig
from runtime.state import VehicleState
from sim.dynamics import PX4_SIH_V1_16, CommandDelay, QuadrotorDynamics, QuadState
from sim.follower.placement import Placement
from sim.response.replay import FlightRecordError, estimate_error, load_flight, load_flights, replay_error
from sim.response.sequence import command_schedule, policy_like_segments
from sim.rotations import quat_from_euler

T0_NS = 5_000_000_000  # the recording host's monotonic clock at the first command
PHYSICS_DT_S, TRUTH_DT_S, ESTIMATE_DT_S = 0.01, 0.02, 0.1
HEADING_RAD = 0.3
PLACEMENT = {"home_local_enu_m": [0.5, -1.0, 0.0], "heading_local_enu_rad": 0.4, "origin_world_enu_m": [2.0, 3.0, 0.0]}


# The follower's placement, whose inverse maps the truth into the autopilot's local frame.
LOCAL = Placement(np.asarray(PLACEMENT["home_local_enu_m"]), PLACEMENT["heading_local_enu_rad"], np.asarray(PLACEMENT["origin_world_enu_m"]))


def _record_flight(run_dir: Path, vel_error_enu_m_s: np.ndarray, pos_error_enu_m: np.ndarray, offboard: bool = True,
                   runtime_bias_enu_m_s: np.ndarray | None = None) -> None:  # fmt: skip
    """Fly the policy-like commands offline; the autopilot holds truth + vel_error at the setpoint.
    ``runtime_bias_enu_m_s``: the runtime measured this bias and logged the estimate less it."""
    bias = np.zeros(3) if runtime_bias_enu_m_s is None else runtime_bias_enu_m_s
    t_cmd, cmd_v, _ = command_schedule(policy_like_segments(duration_s=8.0))
    dynamics, delay = QuadrotorDynamics(PX4_SIH_V1_16), CommandDelay(PX4_SIH_V1_16)
    state = QuadState.at_rest(torch.tensor([[1.0, 1.0, 2.0]], dtype=torch.float64), HEADING_RAD)
    error = torch.as_tensor(vel_error_enu_m_s, dtype=torch.float64).reshape(1, 3)
    truth: dict[str, list] = {"t_s": [], "pos_enu_m": [], "vel_enu_m_s": [], "yaw_enu_rad": []}
    run_dir.mkdir(parents=True)
    recorder = Recorder(run_dir / "flight.mcap", RecorderConfig(flush_period_s=0.2, queue_size=4096))  # faster than real time: drop nothing
    sent = -1
    for i in range(int((t_cmd[-1] + 0.5) / PHYSICS_DT_S)):
        t_s = i * PHYSICS_DT_S
        t_ns = T0_NS + round(t_s * 1e9)
        k = int(np.searchsorted(t_cmd, t_s + 1e-9, side="right")) - 1
        command = cmd_v[max(k, 0)]
        yaw = float(state.yaw_enu_rad()[0])
        if k > sent:  # the runtime sends each command once, at the control rate
            sent = k
            flu = np.array([command[0], command[1], command[2], command[3]])
            mavsdk = VelocityBodyYawspeed(float(command[0]), -float(command[1]), -float(command[2]), -math.degrees(float(command[3])))
            recorder.log_command(t_ns, None, flu, mavsdk, "policy", offboard)
        if i % round(ESTIMATE_DT_S / PHYSICS_DT_S) == 0:
            pos = state.pos_enu_m[0].numpy() + pos_error_enu_m
            vel = state.vel_enu_m_s[0].numpy() + vel_error_enu_m_s
            local_yaw = yaw + PLACEMENT["heading_local_enu_rad"]
            quat = quat_from_euler(torch.zeros(1), torch.zeros(1), torch.tensor([local_yaw]))[0].numpy()
            recorder.log_state(t_ns, VehicleState(pos_enu_m=LOCAL.local_position(pos), vel_enu_m_s=LOCAL.local_from_world(vel - bias),
                                                  vel_bias_enu_m_s=LOCAL.local_from_world(bias),
                                                  t_posvel_ns=t_ns, quat_enu_flu=quat, t_att_ns=t_ns,
                                                  flight_mode="OFFBOARD" if offboard else "POSCTL", in_air=True))  # fmt: skip
        if i % round(TRUTH_DT_S / PHYSICS_DT_S) == 0:
            truth["t_s"].append(t_ns * 1e-9)
            truth["pos_enu_m"].append(state.pos_enu_m[0].tolist())
            truth["vel_enu_m_s"].append(state.vel_enu_m_s[0].tolist())
            truth["yaw_enu_rad"].append(yaw)
        vel_cmd = torch.as_tensor(vehicle_to_world_enu(command[:3], yaw), dtype=torch.float64).reshape(1, 3)
        vel_cmd, yaw_cmd = delay.push(t_s, vel_cmd, torch.tensor([float(command[3])], dtype=torch.float64))
        state = dynamics.step(state, vel_cmd - error, yaw_cmd, PHYSICS_DT_S)  # it holds its estimate at the setpoint
    recorder.close()
    (run_dir / "trace.json").write_text(json.dumps({**truth, "placement": PLACEMENT}))


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("campaign")
    _record_flight(root / "runs" / "a", np.array([0.3, -0.2, 0.1]), np.array([0.2, 0.0, -0.3]))
    _record_flight(root / "runs" / "b", np.array([-0.1, 0.2, -0.1]), np.array([0.0, 0.0, 0.1]),
                   runtime_bias_enu_m_s=np.array([-0.1, 0.15, 0.0]))  # fmt: skip
    _record_flight(root / "runs" / "c-never-in-offboard", np.zeros(3), np.zeros(3), offboard=False)
    return root


def test_the_estimates_error_is_found_in_the_rooms_frame(campaign):
    flights = load_flights([campaign])
    assert [f.name for f in flights] == ["a", "b"]  # c never flew in offboard: left out
    err = estimate_error(flights)
    # Two flights, constant errors: the spread of the per-flight means is half their difference.
    np.testing.assert_allclose(err["bias_sd"]["velocity_m_s"], [0.2, 0.2, 0.1], atol=0.01)
    np.testing.assert_allclose(err["bias_sd"]["position_m"], [0.1, 0.0, 0.2], atol=0.01)
    np.testing.assert_allclose(err["within_flight_sd"]["velocity_m_s"], [0.0, 0.0, 0.0], atol=0.01)
    # As the runtime used it: flight b's velocity less the bias it measured (-0.1, 0.15, 0), a's as is.
    corrected = estimate_error(flights, corrected=True)
    np.testing.assert_allclose(corrected["bias_sd"]["velocity_m_s"], [0.15, 0.125, 0.1], atol=0.01)
    assert corrected["bias_sd"]["position_m"] == err["bias_sd"]["position_m"]


def test_the_model_predicts_the_estimate_the_autopilot_holds_not_the_truth(campaign):
    flights = load_flights([campaign])
    against_estimate = replay_error(flights, PX4_SIH_V1_16, "estimate")["at_s"]["1.0"]["rms"]
    against_truth = replay_error(flights, PX4_SIH_V1_16, "truth")["at_s"]["1.0"]["rms"]
    # Started from the truth, the model flies to the setpoint while the truth settles off it by the
    # estimate's error (0.1-0.3 m/s per axis here); from the estimate it flies as the autopilot did,
    # but for the drag, which acts on the true velocity (0.77 kg/s x 0.3 m/s / 2.7 /s ~ 0.09 m/s).
    assert max(against_estimate[:3]) < 0.09, against_estimate
    assert sum(against_truth[:3]) > 2.5 * sum(against_estimate[:3]), (against_truth, against_estimate)
    assert against_estimate[3] < 0.05  # heading (rad)


def test_unreadable_runs_name_the_file_and_the_fix(campaign, tmp_path):
    with pytest.raises(FlightRecordError, match="trace.json.*cmnav sitl --autopilot"):
        load_flight(tmp_path)
    (tmp_path / "trace.json").write_text((campaign / "runs" / "a" / "trace.json").read_text())
    (tmp_path / "flight.mcap").write_bytes(b"not an mcap")
    with pytest.raises(FlightRecordError, match="flight.mcap.*not an MCAP file"):
        load_flight(tmp_path)
    with pytest.raises(FlightRecordError, match="never flew the policy"):
        load_flight(campaign / "runs" / "c-never-in-offboard")


def test_the_command_prints_and_writes_both(campaign, tmp_path):
    out = tmp_path / "replay.json"
    proc = subprocess.run([sys.executable, "-m", "sim.response", "replay", str(campaign), "-o", str(out)],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "2 flights" in proc.stdout and "replayed against the estimate, 1.0 s ahead" in proc.stdout
    written = json.loads(out.read_text())
    assert set(written["replay"]) == {"truth", "estimate"} and written["estimate_error"]["flights"] == 2
    bad = subprocess.run([sys.executable, "-m", "sim.response", "replay", str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "trace.json" in bad.stderr
