"""`cmnav replay`: a log recorded by the flight loop replays to the same actions; another model,
cut and killed logs, and files that are not flight logs."""

import asyncio
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from runtime.camera import Frame
from runtime.config import RecorderConfig, RuntimeConfig, WatchdogConfig
from runtime.contract import CONTROL_PERIOD_S
from runtime.flight import FlightLoop
from runtime.model import PolicyModel
from runtime.log.recorder import Recorder
from runtime.programs import replay as replay_module
from runtime.programs.replay import ReplayError, replay_log
from tests.runtime.onnx_models import recurrent_step_model, save
from tests.runtime.test_flight_loop import START, KinematicVehicle

ROOT = Path(__file__).resolve().parents[2]
TOLERANCE = 1e-5


class TexturedCamera:
    """15 Hz frames of seeded noise (every frame differs, some depth pixels invalid)."""

    async def start(self):
        pass

    async def frames(self):
        rng = np.random.default_rng(7)
        seq = 0
        while True:
            seq += 1
            depth = rng.uniform(0.3, 12.0, (120, 212)).astype(np.float32)
            depth[rng.random((120, 212)) < 0.1] = 0.0
            gray = rng.integers(0, 256, (120, 212), dtype=np.uint8)
            yield Frame(time.monotonic_ns(), depth, gray, seq)
            await asyncio.sleep(CONTROL_PERIOD_S)

    async def close(self):
        pass


async def _fly_two_episodes(model_path: Path, log_path: Path, on_alive=None) -> list:
    """Two offboard episodes (two GRU resets) of a recurrent model, recorded to one log."""
    config = RuntimeConfig(watchdog=WatchdogConfig(hold_grace_s=0.2), recorder=RecorderConfig(flush_period_s=0.2))
    recorder = Recorder(log_path, config.recorder, metadata=PolicyModel(model_path).log_metadata())
    vehicle = KinematicVehicle()
    await vehicle.start()
    loop = FlightLoop(config, PolicyModel(model_path), vehicle, TexturedCamera(), recorder, on_alive=on_alive)
    await loop.start()
    results = []
    try:
        await loop.wait_first_frame(2.0)
        for goal in (START + np.array([15.0, 5.0, 0.5]), START + np.array([-12.0, 8.0, -0.5])):
            vehicle.mode, vehicle.t_mode_ns = "OFFBOARD", time.monotonic_ns()  # the pilot re-enters offboard
            results.append(await loop.fly(goal, 1.0))
    finally:
        await loop.close()
        vehicle._task.cancel()
        recorder.close()
    return results


@pytest.fixture(scope="module")
def flown(tmp_path_factory):
    """(model, log, episode results) of a recorded two-episode flight."""
    tmp = tmp_path_factory.mktemp("replay")
    model = save(recurrent_step_model(), tmp / "recurrent.onnx")
    log_path = tmp / "flight.mcap"
    results = asyncio.run(_fly_two_episodes(model, log_path))
    return model, log_path, results


def test_same_model_replays_the_recorded_actions(flown):
    model, log_path, results = flown
    report = replay_log(log_path)  # the model path and hash come from the log's metadata
    assert report.model == str(model.resolve()) and report.same_model
    assert report.steps == sum(r.steps for r in results) > 10
    assert report.episodes == 2 and report.steps_without_frame == 0 and report.stopped_early is None
    assert report.max_abs_diff <= TOLERANCE and report.mean_abs_diff <= TOLERANCE
    assert report.max_latent_abs_diff <= TOLERANCE
    assert len(report.per_step_max_abs_diff) == report.steps == len(report.frame_seq)


def test_another_model_shows_differences(flown, tmp_path):
    _, log_path, _ = flown
    other = save(recurrent_step_model(action_offset=0.25), tmp_path / "other.onnx")
    report = replay_log(log_path, other)
    assert not report.same_model
    assert report.max_abs_diff > 0.1 and report.mean_abs_diff > 0.1
    assert json.loads(json.dumps(report.to_json()))["same_model"] is False


def test_a_nan_model_is_refused_not_reported_as_an_infinite_difference(flown, tmp_path):
    _, log_path, _ = flown
    nan_model = save(recurrent_step_model(action_offset=float("nan")), tmp_path / "nan.onnx")
    with pytest.raises(ReplayError, match=r"cannot replay .* outputs NaN/Inf \(action\)"):
        replay_log(log_path, nan_model)


def test_hidden_state_must_follow_the_resets(flown, monkeypatch):
    """Replaying without the flight's GRU resets would not match: the check has teeth."""
    _, log_path, _ = flown

    class NeverReset(replay_module.PolicyMemory):
        def reset(self):
            self.epoch += 1

    monkeypatch.setattr(replay_module, "PolicyMemory", NeverReset)
    assert replay_log(log_path).max_abs_diff > 0.01


@pytest.mark.parametrize("fraction", [0.35, 0.7])
def test_cut_log_replays_a_prefix(flown, tmp_path, fraction):
    _, log_path, _ = flown
    full = replay_log(log_path)
    data = log_path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    report = replay_log(cut)
    assert 0 < report.steps < full.steps
    assert report.frame_seq == full.frame_seq[: report.steps]
    assert report.max_abs_diff <= TOLERANCE
    assert "ends early" in report.stopped_early


KILLED_FLIGHT = textwrap.dedent(
    """
    import asyncio, sys
    sys.path.insert(0, {root!r})
    from tests.runtime.test_replay import _fly_two_episodes
    asyncio.run(_fly_two_episodes(sys.argv[1], sys.argv[2], on_alive=lambda: print("step", flush=True)))
    """
)


def test_sigkilled_flight_replays_up_to_its_last_chunk(flown, tmp_path):
    model, _, _ = flown
    log_path = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-c", KILLED_FLIGHT.format(root=str(ROOT)), str(model), str(log_path)],
                            stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        steps_seen = 0
        while steps_seen < 12:  # the recorder flushes every 0.2 s: several chunks are complete by now
            assert proc.stdout.readline(), f"the flight exited early with {proc.wait()}"
            steps_seen += 1
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    report = replay_log(log_path)
    assert report.steps > 0 and report.max_abs_diff <= TOLERANCE
    assert "ends early" in report.stopped_early


def test_random_bytes_are_not_a_flight_log(tmp_path):
    path = tmp_path / "noise.mcap"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(ReplayError, match=r"noise\.mcap is not an MCAP file"):
        replay_log(path)


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ReplayError, match="cannot read flight log .*nowhere.mcap"):
        replay_log(tmp_path / "nowhere.mcap")


def test_foreign_mcap_is_refused(tmp_path):
    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="someone else")
        schema = writer.register_schema("Thing", "jsonschema", b"{}")
        channel = writer.register_channel("/camera/depth", "json", schema)
        writer.add_message(channel, log_time=1, publish_time=1, data=b"{}")
        writer.finish()
    with pytest.raises(ReplayError, match=r"foreign\.mcap has no 'cmnav' metadata record .*not a flight log written by cmnav"):
        replay_log(path)


def test_log_without_policy_steps_names_the_missing_channels(tmp_path):
    path = tmp_path / "frames_only.mcap"
    recorder = Recorder(path, RecorderConfig(flush_period_s=0.2), metadata={"model": "m.onnx"})
    depth = np.ones((120, 212), np.float32)
    recorder.log_frame(Frame(time.monotonic_ns(), depth, np.zeros((120, 212), np.uint8), 1))
    recorder.close()
    with pytest.raises(ReplayError, match="lacks the channel.*/policy/observation, /policy/action"):
        replay_log(path)


def test_cli_reports_and_refuses(flown, tmp_path):
    _, log_path, _ = flown
    ok = subprocess.run([sys.executable, "-m", "cmnav", "replay", str(log_path), "--json"], capture_output=True,
                        text=True, timeout=60, cwd=ROOT)  # fmt: skip
    assert ok.returncode == 0, ok.stderr[-2000:]
    report = json.loads(ok.stdout.strip().splitlines()[-1])
    assert report["steps"] > 10 and report["max_abs_diff"] <= TOLERANCE and report["same_model"]
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap at all")
    refused = subprocess.run([sys.executable, "-m", "cmnav", "replay", str(bad)], capture_output=True, text=True,
                             timeout=60, cwd=ROOT)  # fmt: skip
    assert refused.returncode == 2
    assert "bad.mcap is not an MCAP file" in refused.stderr and "Traceback" not in refused.stderr
