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
from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.reader import NonSeekingReader, make_reader
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap_protobuf.decoder import DecoderFactory

from runtime.camera import Frame
from runtime.config import RecorderConfig
from runtime.contract import action_to_mavsdk, action_to_velocity_flu
from runtime.model import ModelOutput
from runtime.policy_step import StepInputs, StepResult
from runtime.log.topics import (
    TOPIC_ACTION, TOPIC_COMMAND, TOPIC_DEPTH, TOPIC_GRAY, TOPIC_LATENT, TOPIC_OBSERVATION, TOPIC_STATE,
    TOPIC_TIMING, TOPIC_WATCHDOG,
)  # fmt: skip
from runtime.log.recorder import Recorder, RecorderError
from runtime.state import VehicleState

ALL_TOPICS = {TOPIC_DEPTH, TOPIC_GRAY, TOPIC_STATE, TOPIC_OBSERVATION, TOPIC_ACTION, TOPIC_COMMAND,
              TOPIC_LATENT, TOPIC_TIMING, TOPIC_WATCHDOG}  # fmt: skip


class JsonDecoderFactory(McapDecoderFactory):
    def decoder_for(self, message_encoding, schema):
        return json.loads if message_encoding == "json" else None


DECODERS = [DecoderFactory(), JsonDecoderFactory()]


def _frame(seq: int, t_ns: int) -> Frame:
    depth = np.linspace(0.0, 9.0, 120 * 212, dtype=np.float32).reshape(120, 212)
    depth[0, :10] = np.nan
    gray = (np.arange(120 * 212) % 256).astype(np.uint8).reshape(120, 212)
    return Frame(t_capture_ns=t_ns, depth_m=depth, gray_u8=gray, seq=seq)


def _log_one_step(rec: Recorder, seq: int, t_ns: int) -> None:
    frame = _frame(seq, t_ns)
    rec.log_frame(frame)
    rec.log_state(t_ns, VehicleState(pos_enu_m=np.array([1.0, 2.0, 3.0]), t_posvel_ns=t_ns, flight_mode="OFFBOARD"))
    action = np.array([0.5, np.nan, -0.2])
    inputs = StepInputs(
        pos_enu_m=np.array([1.0, 2.0, 3.0]), quat_enu_flu=np.array([1.0, 0, 0, 0]), vel_body_flu_m_s=np.zeros(3),
        angvel_body_flu_rad_s=np.zeros(3), goal_enu_m=np.array([9.0, 2.0, 3.0]), hidden=np.zeros(8, np.float32),
        prev_action=np.zeros(3, np.float32), hidden_epoch=1,
    )  # fmt: skip
    output = ModelOutput(action=action, hidden_next=np.zeros(8, np.float32), latent=np.ones(64, np.float32))
    rec.log_step(frame, StepResult(inputs, np.arange(15, dtype=np.float32), output, np.clip(action, -1, 1), 0, 0, 0))
    clean = np.array([0.5, 0.1, -0.2])
    rec.log_command(t_ns, frame, action_to_velocity_flu(clean), action_to_mavsdk(clean), "policy", True)
    rec.log_timing(frame, {"preprocess": 1.5, "inference": 2.25, "step": 4.0}, missed_deadline=False)


def test_every_channel_reads_back(tmp_path):
    path = tmp_path / "logs" / "flight.mcap"
    rec = Recorder(path, RecorderConfig(flush_period_s=0.2), metadata={"model": "m.onnx"})
    t0 = time.monotonic_ns()
    for k in range(5):
        _log_one_step(rec, k + 1, t0 + k * 66_666_667)
    rec.log_watchdog(t0, {"event": "start", "cause": None})
    rec.close()
    assert rec.stats.dropped == 0

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=DECODERS)
        summary = reader.get_summary()
        assert {c.topic for c in summary.channels.values()} == ALL_TOPICS
        assert {s.name for s in summary.schemas.values()} >= {"foxglove.RawImage", "cmnav.VehicleState", "cmnav.Action"}
        messages: dict[str, list] = {}
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            messages.setdefault(channel.topic, []).append((message, decoded))
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert meta["cmnav"]["model"] == "m.onnx"
    offset = int(meta["cmnav"]["monotonic_to_unix_offset_ns"])
    assert {t: len(v) for t, v in messages.items()} == {**{t: 5 for t in ALL_TOPICS}, TOPIC_WATCHDOG: 1}

    depth_msg, depth = messages[TOPIC_DEPTH][-1]
    assert depth_msg.log_time == t0 + 4 * 66_666_667 + offset
    assert (depth.width, depth.height, depth.encoding, depth.frame_id) == (212, 120, "32FC1", "camera")
    depth_m = np.frombuffer(depth.data, "<f4").reshape(120, 212)
    np.testing.assert_array_equal(depth_m, _frame(5, 0).depth_m)  # NaN (invalid) survives
    _, gray = messages[TOPIC_GRAY][0]
    assert gray.encoding == "mono8"
    np.testing.assert_array_equal(np.frombuffer(gray.data, np.uint8).reshape(120, 212), _frame(1, 0).gray_u8)

    action = messages[TOPIC_ACTION][0][1]
    assert action["raw"] == [0.5, None, -0.2] and action["frame_seq"] == 1
    observation = messages[TOPIC_OBSERVATION][0][1]
    assert len(observation["observation"]) == 79 and observation["observation"][15:] == [1.0] * 64
    assert observation["hidden_epoch"] == 1 and observation["goal_enu_m"] == [9.0, 2.0, 3.0]
    assert len(messages[TOPIC_LATENT][0][1]["latent"]) == 64
    command = messages[TOPIC_COMMAND][0][1]
    assert command["source"] == "policy" and command["yawspeed_deg_s"] == pytest.approx(12.0)
    assert messages[TOPIC_TIMING][0][1]["stages_ms"]["inference"] == 2.25
    state = messages[TOPIC_STATE][0][1]
    assert state["pos_enu_m"] == [1.0, 2.0, 3.0] and state["flight_mode"] == "OFFBOARD"


def test_unwritable_log_dir_named(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(RecorderError, match="cannot create flight log"):
        Recorder(blocker / "flight.mcap")


WRITER = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {root!r})
    sys.path.insert(0, {tests!r})
    from test_recorder import _log_one_step
    from runtime.config import RecorderConfig
    from runtime.log.recorder import Recorder

    rec = Recorder(sys.argv[1], RecorderConfig(flush_period_s=0.5))
    rec.log_watchdog(time.monotonic_ns(), {{"event": "start"}})
    seq = 0
    while True:
        seq += 1
        _log_one_step(rec, seq, time.monotonic_ns())
        print(seq, flush=True)
        time.sleep(1 / 15)
    """
)


def test_sigkilled_writer_loses_at_most_about_a_second(tmp_path):
    path = tmp_path / "killed.mcap"
    script = WRITER.format(root=str(Path.cwd()), tests=str(Path(__file__).parent))
    proc = subprocess.Popen([sys.executable, "-c", script, str(path)], stdout=subprocess.PIPE, text=True)
    try:
        last_logged = 0
        while last_logged < 40:  # ~2.7 s of flight at 15 Hz
            line = proc.stdout.readline()
            assert line, f"writer exited early with {proc.wait()}"
            last_logged = int(line)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()

    seqs: dict[str, int] = {}
    with open(path, "rb") as f:
        # A killed log has no summary: stream it (make_reader on a non-seekable stream does the same).
        # It ends in a cut record, or in the unfinished chunk whose length is still a placeholder.
        reader = NonSeekingReader(f, decoder_factories=DECODERS)
        with pytest.raises((EndOfFile, RecordLengthLimitExceeded)):
            for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
                if channel.topic in (TOPIC_DEPTH, TOPIC_GRAY, TOPIC_STATE):
                    seqs[channel.topic] = seqs.get(channel.topic, 0) + 1
                elif channel.topic != TOPIC_WATCHDOG:
                    seqs[channel.topic] = max(seqs.get(channel.topic, 0), decoded["frame_seq"])
                else:
                    seqs[channel.topic] = 1
    assert set(seqs) == ALL_TOPICS
    # Flushed every 0.5 s: at most ~1 s (15 frames) lost, with slack for a loaded machine.
    del seqs[TOPIC_WATCHDOG]
    assert min(seqs.values()) >= last_logged - 23, seqs


class FailingWriter:
    """Stands in for foxglove's MCAP writer after the disk filled: every write method raises the
    RuntimeError foxglove raises (the recorder's own code path is unchanged around it)."""

    ERROR = "FoxgloveError: MCAP error: I/O error from writing, or reading a compression stream"

    def __init__(self, real) -> None:
        self._real = real

    def write_metadata(self, *args, **kwargs):
        raise RuntimeError(self.ERROR)

    def flush(self):
        raise RuntimeError(self.ERROR)

    def close(self):
        self._real.close()  # release the real file
        raise RuntimeError("FoxgloveError: MCAP error: attempted another write after a write method failed")


def test_a_write_failure_is_logged_once_counted_and_never_raises(tmp_path, caplog):
    rec = Recorder(tmp_path / "log.mcap", RecorderConfig(flush_period_s=0.05))
    rec._writer = FailingWriter(rec._writer)  # the disk fills after the log opened
    for seq in range(1, 40):
        _log_one_step(rec, seq, time.monotonic_ns())
        time.sleep(0.005)
    rec.close()  # must not raise, although the writer's close does
    rec.close()
    assert rec.stats.log_error is not None and "I/O error" in rec.stats.log_error
    assert rec.stats.dropped > 0
    assert sum("flight log: writing" in r.getMessage() for r in caplog.records) == 1


def test_a_failure_to_write_the_first_record_refuses_at_open(tmp_path, monkeypatch):
    import foxglove

    real_open = foxglove.open_mcap
    monkeypatch.setattr(foxglove, "open_mcap", lambda *a, **k: FailingWriter(real_open(*a, **k)))
    with pytest.raises(RecorderError, match="cannot create flight log .* has free space"):
        Recorder(tmp_path / "log.mcap")


@pytest.fixture
def full_tmpfs(tmp_path):
    """A 1 MiB tmpfs, filled, where this user may mount one (root in a container); else skip."""
    mount_point = tmp_path / "tmpfs"
    mount_point.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount_point)], capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({proc.stderr.strip() or proc.returncode}); the injected failures above cover the path")
    try:
        with open(mount_point / "filler", "wb") as f:
            try:
                while True:
                    f.write(b"\0" * 65536)
                    f.flush()
            except OSError:
                pass  # ENOSPC: full
        yield mount_point
    finally:
        subprocess.run(["umount", str(mount_point)], check=True)


def test_a_really_full_disk_refuses_at_open(full_tmpfs):
    with pytest.raises(RecorderError, match="cannot create flight log"):
        Recorder(full_tmpfs / "log.mcap")


def test_a_disk_that_fills_while_recording_costs_records_only(full_tmpfs):
    (full_tmpfs / "filler").write_bytes(b"\0" * (1024 * 1024 - 200_000))  # leave ~200 kB free
    rec = Recorder(full_tmpfs / "log.mcap", RecorderConfig(flush_period_s=0.05))
    for seq in range(1, 60):
        _log_one_step(rec, seq, time.monotonic_ns())
        time.sleep(0.01)
    rec.close()
    assert rec.stats.log_error is not None and rec.stats.dropped > 0 and rec.stats.written > 0


def test_writer_thread_keeps_normal_priority(tmp_path):
    """The writer holds the GIL while it encodes: demoted (SCHED_IDLE, nice), it would keep it for
    as long as other processes take its core, and the control path would wait behind it
    (runtime.service.affinity)."""
    rec = Recorder(tmp_path / "flight.mcap", RecorderConfig(flush_period_s=0.2))
    try:
        _log_one_step(rec, 1, time.monotonic_ns())
        deadline = time.monotonic() + 5.0
        while rec.stats.written == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert rec.stats.written > 0
        assert os.sched_getscheduler(rec._thread.native_id) == os.sched_getscheduler(0) == os.SCHED_OTHER
        assert os.getpriority(os.PRIO_PROCESS, rec._thread.native_id) == os.getpriority(os.PRIO_PROCESS, 0)
    finally:
        rec.close()
