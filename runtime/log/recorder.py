"""The MCAP flight log, written with the Foxglove SDK (open it in Foxglove).

Channels (topic: schema):
- ``/camera/depth``: ``foxglove.RawImage`` 32FC1, the raw camera depth in metres (0/NaN = invalid)
- ``/camera/gray``: ``foxglove.RawImage`` mono8
- ``/vehicle/state``: ``cmnav.VehicleState`` (local ENU world, FLU body, receive times)
- ``/policy/observation``: ``cmnav.Observation`` (15 state values + 64 latent = 79, and what the
  step was computed from: telemetry, goal and GRU reset count, so ``cmnav replay`` can redo it)
- ``/policy/action``: ``cmnav.Action`` (raw and clipped, in [-1, 1])
- ``/vehicle/command``: ``cmnav.VelocityCommand`` (body FLU and MAVSDK FRD forms)
- ``/policy/latent``: ``cmnav.Latent`` (64)
- ``/timing``: ``cmnav.StepTiming`` (per-stage milliseconds of each step)
- ``/watchdog``: ``cmnav.WatchdogEvent`` (supervision start with thresholds, trips, Hold)
- ``/vehicle/status_text``: ``cmnav.StatusText`` (the autopilot's STATUSTEXTs, severity and text)

Log times: the runtime's clock is CLOCK_MONOTONIC; MCAP log times are Unix-epoch nanoseconds, so
each monotonic time is shifted by one offset taken when the log opens (kept in the file's
``cmnav`` metadata record as ``monotonic_to_unix_offset_ns``).  Messages also carry their
monotonic times in their fields.

The flight loop must never wait on the disk: every ``log_*`` call only puts a record into a
bounded queue (dropped and counted when full) and a writer thread encodes, compresses (zstd) and
writes.  The recorder is a best-effort observer: a failure to write or close the log (full disk,
I/O error, foxglove's ``RuntimeError``) is logged once, kept in ``stats.log_error``, and from then
on records are dropped and counted — it never raises into the flight.  Only opening raises
(:class:`RecorderError`), so that a program can refuse to fly unrecorded before offboard.  The writer flushes (closes the chunk) at least every ``flush_period_s``, so a killed
process loses about that much.  A log cut short by a kill has no summary section: read it with a
streaming reader (``mcap.reader.NonSeekingReader``, ``iter_messages(log_time_order=False)``), which
yields every message of every finished chunk, then raises ``mcap.exceptions.EndOfFile`` at the cut
(or ``RecordLengthLimitExceeded`` at the unfinished chunk, whose length is still a placeholder).
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import foxglove
import numpy as np
from foxglove.channels import RawImageChannel
from foxglove.mcap import MCAPCompression, MCAPWriteOptions
from foxglove.messages import RawImage, Timestamp

from ..camera.frame import Frame
from ..config import RecorderConfig
from ..contract import CONTRACT_VERSION, VelocityBodyYawspeed
from ..policy_step import StepResult
from ..state import StatusText, VehicleState
from .topics import (
    CAMERA_FRAME_ID,
    METADATA_NAME,
    TOPIC_ACTION,
    TOPIC_COMMAND,
    TOPIC_DEPTH,
    TOPIC_GRAY,
    TOPIC_LATENT,
    TOPIC_OBSERVATION,
    TOPIC_STATE,
    TOPIC_STATUS_TEXT,
    TOPIC_TIMING,
    TOPIC_WATCHDOG,
)

log = logging.getLogger(__name__)
# foxglove reports a failed channel write here (one warning per message) instead of raising.
_FOXGLOVE_SINK_LOG = logging.getLogger("foxglove.log_sink_set")


_NUM_ARRAY = {"type": "array", "items": {"type": ["number", "null"]}}
_INT = {"type": "integer"}
_SCHEMAS: dict[str, tuple[str, str, dict[str, Any]]] = {
    TOPIC_STATE: ("cmnav.VehicleState", "Vehicle telemetry: local ENU world, FLU body; t_*_ns = receive times (CLOCK_MONOTONIC)", {
        "t_ns": _INT, "pos_enu_m": _NUM_ARRAY, "vel_enu_m_s": _NUM_ARRAY, "vel_body_flu_m_s": _NUM_ARRAY,
        "vel_bias_enu_m_s": _NUM_ARRAY, "quat_enu_flu": _NUM_ARRAY, "angvel_body_flu_rad_s": _NUM_ARRAY, "yaw_enu_rad": {"type": ["number", "null"]},
        "height_above_home_m": {"type": ["number", "null"]}, "flight_mode": {"type": "string"},
        "armed": {"type": "boolean"}, "in_air": {"type": "boolean"}, "landed_state": {"type": "string"},
        "t_posvel_ns": _INT, "t_att_ns": _INT, "t_mode_ns": _INT}),
    TOPIC_OBSERVATION: ("cmnav.Observation", "Policy observation: [0:15] state (runtime.contract.observation), [15:79] latent; "
                        "the step's inputs: telemetry (local ENU world, FLU body), goal (local ENU, m), hidden_epoch = GRU resets so far", {
        "t_capture_ns": _INT, "frame_seq": _INT, "observation": _NUM_ARRAY, "hidden_epoch": _INT,
        "pos_enu_m": _NUM_ARRAY, "quat_enu_flu": _NUM_ARRAY, "vel_body_flu_m_s": _NUM_ARRAY,
        "angvel_body_flu_rad_s": _NUM_ARRAY, "goal_enu_m": _NUM_ARRAY}),
    TOPIC_ACTION: ("cmnav.Action", "Policy action: raw ONNX output and clipped to [-1, 1] (null = NaN/Inf)", {
        "t_capture_ns": _INT, "frame_seq": _INT, "raw": _NUM_ARRAY, "clipped": _NUM_ARRAY}),
    TOPIC_COMMAND: ("cmnav.VelocityCommand", "Velocity command: body FLU (m/s, rad/s) and MAVSDK FRD form (m/s, deg/s)", {
        "t_capture_ns": _INT, "frame_seq": _INT, "source": {"type": "string"}, "sent": {"type": "boolean"},
        "vel_body_flu_m_s": _NUM_ARRAY, "yaw_rate_flu_rad_s": {"type": "number"}, "forward_m_s": {"type": "number"},
        "right_m_s": {"type": "number"}, "down_m_s": {"type": "number"}, "yawspeed_deg_s": {"type": "number"}}),
    TOPIC_LATENT: ("cmnav.Latent", "CMWAE latent z (64)", {
        "t_capture_ns": _INT, "frame_seq": _INT, "latent": _NUM_ARRAY}),
    TOPIC_TIMING: ("cmnav.StepTiming", "Per-stage time of one policy step (ms); step_ms = frame taken -> command sent", {
        "t_capture_ns": _INT, "frame_seq": _INT, "missed_deadline": {"type": "boolean"},
        "stages_ms": {"type": "object", "additionalProperties": {"type": "number"}}}),
    TOPIC_WATCHDOG: ("cmnav.WatchdogEvent", "Watchdog: supervision start (thresholds), trips and Hold", {
        "event": {"type": "string"}, "cause": {"type": ["string", "null"]}, "detail": {"type": ["string", "null"]},
        "t_s": {"type": ["number", "null"]}, "detect_ms": {"type": ["number", "null"]},
        "response": {"type": ["string", "null"]}, "hold_t_s": {"type": ["number", "null"]}}),
    TOPIC_STATUS_TEXT: ("cmnav.StatusText", "The autopilot's STATUSTEXT: MAV_SEVERITY name, text; t_ns = receive time "
                        "(CLOCK_MONOTONIC), seq = order of receipt", {
        "t_ns": _INT, "seq": _INT, "severity": {"type": "string"}, "text": {"type": "string"}}),
}  # fmt: skip


class RecorderError(RuntimeError):
    """The flight log could not be opened or written."""


@dataclass
class RecorderStats:
    written: int = 0
    dropped: int = 0  # queue full, or after a write failure
    flushes: int = 0
    log_error: str | None = None  # the first failure to write or close the log (None: none)


_STOP = object()


class Recorder:
    """Writes the flight log from a background thread; ``log_*`` never blocks the caller."""

    def __init__(self, path: str | Path, config: RecorderConfig = RecorderConfig(), metadata: dict[str, str] | None = None) -> None:
        """Create ``path`` (must not exist; parent directories are created)."""
        self.path = Path(path)
        self.config = config
        self.stats = RecorderStats()
        self._offset_ns = time.time_ns() - time.monotonic_ns()
        self._queue: queue.Queue = queue.Queue(maxsize=config.queue_size)
        self._context = foxglove.Context()
        self._writer = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = foxglove.open_mcap(
                self.path,
                context=self._context,
                writer_options=MCAPWriteOptions(compression=MCAPCompression.Zstd, compression_threads=0),
            )
            # Written at once: a full disk shows here, before the flight, not in the air.
            self._writer.write_metadata(
                METADATA_NAME,
                {"contract_version": CONTRACT_VERSION, "monotonic_to_unix_offset_ns": str(self._offset_ns), **(metadata or {})},
            )
            self._writer.flush()
        except (OSError, RuntimeError) as err:  # foxglove raises RuntimeError (FoxgloveError) for I/O errors
            self._discard_writer()
            raise RecorderError(f"cannot create flight log {self.path} ({err}): check the log directory exists, "
                                "is writable and has free space") from err  # fmt: skip
        self._images = {
            TOPIC_DEPTH: RawImageChannel(TOPIC_DEPTH, context=self._context),
            TOPIC_GRAY: RawImageChannel(TOPIC_GRAY, context=self._context),
        }
        self._json = {
            topic: foxglove.Channel(
                topic,
                schema=foxglove.Schema(
                    name=name,
                    encoding="jsonschema",
                    data=json.dumps({"title": name, "description": doc, "type": "object", "properties": props}).encode(),
                ),
                message_encoding="json",
                context=self._context,
            )
            for topic, (name, doc, props) in _SCHEMAS.items()
        }
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="mcap_recorder", daemon=True)
        _FOXGLOVE_SINK_LOG.addFilter(self._sink_filter)
        self._thread.start()
        log.info("recording flight log to %s", self.path)

    # ------------------------------------------------------------------ what the loop logs

    def log_frame(self, frame: Frame) -> None:
        """The raw camera frame: depth (metres) and gray, stamped with its capture time."""
        self._put(("frame", frame.t_capture_ns, frame))

    def log_state(self, t_ns: int, state: VehicleState) -> None:
        self._put(("state", t_ns, state))

    def log_step(self, frame: Frame, step: StepResult) -> None:
        """One policy step's inputs, observation (79), actions (3) and latent (64), stamped with the frame."""
        self._put(("step", frame.t_capture_ns, (frame.seq, step)))

    def log_command(
        self, t_ns: int, frame: Frame | None, cmd_flu: np.ndarray, cmd: VelocityBodyYawspeed, source: str, sent: bool
    ) -> None:
        """A velocity command: ``cmd_flu`` (vx, vy, vz m/s, wz rad/s) and its MAVSDK form."""
        self._put(("command", t_ns, (frame, cmd_flu, cmd, source, sent)))

    def log_timing(self, frame: Frame, stages_ms: dict[str, float], missed_deadline: bool) -> None:
        self._put(("timing", frame.t_capture_ns, (frame.seq, dict(stages_ms), missed_deadline)))

    def log_watchdog(self, t_ns: int, event: dict) -> None:
        self._put(("watchdog", t_ns, dict(event)))

    def log_status_text(self, text: StatusText) -> None:
        """One of the autopilot's STATUSTEXTs, stamped with its receive time."""
        self._put(("status_text", text.t_ns, text))

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is queued, then close the file (its summary makes it seekable).  Never raises:
        a failure is logged once and kept in ``stats.log_error``.  The writer thread gets
        ``timeout_s``; the file's close itself can block on a hung disk, so callers in the flight
        program run this in a daemon thread with a bound (``runtime.service.shutdown``)."""
        if self._closed:
            return
        self._closed = True
        if self._thread.is_alive():
            try:
                self._queue.put(_STOP, timeout=timeout_s)
            except queue.Full:
                log.error("flight log writer is stuck; closing %s without the queued records", self.path)
            self._thread.join(timeout_s)
        if self._thread.is_alive():
            self._fail(f"the writer did not finish within {timeout_s:.1f} s; {self.path} may lack its summary")
            return
        try:
            self._writer.close()
        except (OSError, RuntimeError) as err:
            self._fail(f"closing {self.path} failed: {err}")
        finally:
            _FOXGLOVE_SINK_LOG.removeFilter(self._sink_filter)
        log.info("flight log %s closed: %d records written, %d dropped%s", self.path, self.stats.written, self.stats.dropped,
                 f" (log error: {self.stats.log_error})" if self.stats.log_error else "")  # fmt: skip

    def _fail(self, message: str) -> None:
        """Keep and log the first failure; later ones (consequences of the first) only at debug level."""
        if self.stats.log_error is None:
            self.stats.log_error = message
            log.error("flight log: %s; the flight goes on, further records are dropped and counted", message)
        else:
            log.debug("flight log: %s", message)

    def _sink_filter(self, record: logging.LogRecord) -> bool:
        """A failed write that foxglove only logs: fail the recorder (once) instead of a warning per message."""
        if threading.current_thread() is not self._thread:
            return True
        self._fail(f"writing {self.path} failed: {record.getMessage()}")
        return False

    def _discard_writer(self) -> None:
        """Close a writer whose first write failed (an unclosed one aborts the interpreter's exit)."""
        if self._writer is None:
            return
        try:
            self._writer.close()
        except (OSError, RuntimeError) as err:
            log.debug("closing the failed flight log %s: %s", self.path, err)

    # ------------------------------------------------------------------ writer thread

    def _put(self, item: tuple) -> None:
        if self.stats.log_error is not None:
            self.stats.dropped += 1
            return
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.stats.dropped += 1
            if self.stats.dropped in (1, 10, 100) or self.stats.dropped % 1000 == 0:
                log.warning("flight log writer is behind: %d records dropped so far", self.stats.dropped)

    def _run(self) -> None:
        try:
            if self._write_until_stopped():
                return
        except (OSError, RuntimeError) as err:  # full disk, I/O error (foxglove: RuntimeError)
            self._fail(f"writing {self.path} failed: {err}")
        except Exception as err:  # noqa: BLE001 - an encoding bug must not stop the observer silently either
            log.exception("flight log writer failed")
            self._fail(f"writing {self.path} failed: {err!r}")
        # Stay until close(): count what the loop still queued as dropped.
        while self._queue.get() is not _STOP:
            self.stats.dropped += 1

    def _write_until_stopped(self) -> bool:
        """Write until close() (True) or a write failure foxglove only logged (False)."""
        next_flush = time.monotonic() + self.config.flush_period_s
        while True:
            try:
                item = self._queue.get(timeout=max(0.0, next_flush - time.monotonic()))
            except queue.Empty:
                item = None
            if item is _STOP:
                return True
            if item is not None:
                self._write(*item)
                if self.stats.log_error is not None:
                    self.stats.dropped += 1
                    return False  # foxglove logged the write as failed (see _sink_filter)
                self.stats.written += 1
            if time.monotonic() >= next_flush:
                self._writer.flush()
                self.stats.flushes += 1
                next_flush = time.monotonic() + self.config.flush_period_s

    def _write(self, kind: str, t_ns: int, payload: Any) -> None:
        log_time = t_ns + self._offset_ns
        if kind == "frame":
            self._write_frame(payload, log_time)
        elif kind == "state":
            self._log_json(TOPIC_STATE, log_time, _state_message(t_ns, payload))
        elif kind == "step":
            seq, step = payload
            head = {"t_capture_ns": t_ns, "frame_seq": seq}
            out, inputs = step.output, step.inputs
            self._log_json(TOPIC_OBSERVATION, log_time, {
                **head, "observation": _floats(np.concatenate([step.observation_state, out.latent])),
                "hidden_epoch": inputs.hidden_epoch, "pos_enu_m": _floats(inputs.pos_enu_m),
                "quat_enu_flu": _floats(inputs.quat_enu_flu), "vel_body_flu_m_s": _floats(inputs.vel_body_flu_m_s),
                "angvel_body_flu_rad_s": _floats(inputs.angvel_body_flu_rad_s), "goal_enu_m": _floats(inputs.goal_enu_m),
            })  # fmt: skip
            self._log_json(TOPIC_ACTION, log_time, {**head, "raw": _floats(out.action), "clipped": _floats(step.action_clipped)})
            self._log_json(TOPIC_LATENT, log_time, {**head, "latent": _floats(out.latent)})
        elif kind == "command":
            frame, cmd_flu, cmd, source, sent = payload
            self._log_json(TOPIC_COMMAND, log_time, {
                "t_capture_ns": frame.t_capture_ns if frame else 0, "frame_seq": frame.seq if frame else 0,
                "source": source, "sent": sent, "vel_body_flu_m_s": _floats(cmd_flu[:3]),
                "yaw_rate_flu_rad_s": float(cmd_flu[3]), "forward_m_s": cmd.forward_m_s, "right_m_s": cmd.right_m_s,
                "down_m_s": cmd.down_m_s, "yawspeed_deg_s": cmd.yawspeed_deg_s,
            })  # fmt: skip
        elif kind == "timing":
            seq, stages, missed = payload
            self._log_json(TOPIC_TIMING, log_time, {"t_capture_ns": t_ns, "frame_seq": seq, "missed_deadline": missed,
                                                    "stages_ms": {k: round(v, 4) for k, v in stages.items()}})  # fmt: skip
        elif kind == "watchdog":
            self._log_json(TOPIC_WATCHDOG, log_time, payload)
        elif kind == "status_text":
            self._log_json(TOPIC_STATUS_TEXT, log_time, {"t_ns": t_ns, "seq": payload.seq, "severity": payload.severity,
                                                         "text": payload.text})  # fmt: skip
        else:
            raise AssertionError(f"unknown record kind {kind!r}")

    def _write_frame(self, frame: Frame, log_time: int) -> None:
        stamp = Timestamp(sec=log_time // 1_000_000_000, nsec=log_time % 1_000_000_000)
        depth = np.ascontiguousarray(frame.depth_m, dtype="<f4")
        gray = np.ascontiguousarray(frame.gray_u8, dtype=np.uint8)
        height, width = depth.shape
        self._images[TOPIC_DEPTH].log(
            RawImage(timestamp=stamp, frame_id=CAMERA_FRAME_ID, width=width, height=height, encoding="32FC1",
                     step=4 * width, data=depth.tobytes()),
            log_time=log_time,
        )  # fmt: skip
        self._images[TOPIC_GRAY].log(
            RawImage(timestamp=stamp, frame_id=CAMERA_FRAME_ID, width=width, height=height, encoding="mono8",
                     step=width, data=gray.tobytes()),
            log_time=log_time,
        )  # fmt: skip

    def _log_json(self, topic: str, log_time: int, message: dict) -> None:
        self._json[topic].log(json.dumps(message, allow_nan=False).encode(), log_time=log_time)


def _floats(values: Any) -> list[float | None]:
    """JSON numbers; NaN/Inf become null (JSON has no NaN)."""
    return [float(v) if math.isfinite(v) else None for v in np.asarray(values, dtype=np.float64).ravel()]


def _number(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _state_message(t_ns: int, s: VehicleState) -> dict:
    return {
        "t_ns": t_ns,
        "pos_enu_m": _floats(s.pos_enu_m),
        "vel_enu_m_s": _floats(s.vel_enu_m_s),
        "vel_body_flu_m_s": _floats(s.vel_body_flu_m_s),
        "vel_bias_enu_m_s": _floats(s.vel_bias_enu_m_s),  # the autopilot's velocity = vel_enu_m_s + this
        "quat_enu_flu": _floats(s.quat_enu_flu),
        "angvel_body_flu_rad_s": _floats(s.angvel_body_flu_rad_s),
        "yaw_enu_rad": _number(s.yaw_enu_rad),
        "height_above_home_m": _number(s.height_above_home_m),
        "flight_mode": s.flight_mode,
        "armed": s.armed,
        "in_air": s.in_air,
        "landed_state": s.landed_state,
        "t_posvel_ns": s.t_posvel_ns,
        "t_att_ns": s.t_att_ns,
        "t_mode_ns": s.t_mode_ns,
    }
