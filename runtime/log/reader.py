"""Reading a cmnav flight log (MCAP, written by ``runtime.log.recorder``) back, front to back.

Used by ``cmnav replay`` and by the ``replay`` camera source.  The file is streamed
(``mcap.stream_reader.StreamReader``) rather than read through its summary: a log cut short by a
killed process has no summary, but every chunk it finished is complete and CRC-checked, so
streaming yields all of them and then stops at the cut (``EndOfFile``, a truncated record, or the
unfinished chunk whose length is still a placeholder).  :attr:`FlightLogReader.stopped_early`
says where and why it stopped.

Times: the log's message times are Unix-epoch ns; the recorder shifted the runtime's
CLOCK_MONOTONIC times by ``monotonic_to_unix_offset_ns`` (kept in the ``cmnav`` metadata record,
written before the first message).  Records yielded here carry the recording host's monotonic
``t_capture_ns``, as the flight loop saw it.  Values the recorder wrote as JSON ``null``
(NaN/Inf) come back as NaN.
"""

from __future__ import annotations

import json
import logging
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import zstandard
from mcap.exceptions import EndOfFile, InvalidMagic, McapError, RecordLengthLimitExceeded
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory

from ..contract import CONTRACT_VERSION
from .topics import METADATA_NAME, TOPIC_DEPTH, TOPIC_GRAY, TOPIC_OBSERVATION

log = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
# Larger than any chunk the recorder writes (a few MB), far below the placeholder length of the
# chunk a killed writer left unfinished.
MAX_RECORD_BYTES = 1 << 30
# Where the byte stream ended before the MCAP footer: a cut file (killed writer, copy cut short).
_CUT = (EndOfFile, RecordLengthLimitExceeded, struct.error)
# Where it is damaged: a chunk whose bytes changed since they were written.
_DAMAGED = (CRCValidationError, zstandard.ZstdError, McapError)


class ReplayError(ValueError):
    """A file is not a readable cmnav flight log; the message names the file, what is wrong and the fix."""


@dataclass(frozen=True)
class LoggedFrame:
    """A recorded camera frame: raw depth (m, float32, 0/NaN = invalid) and gray (uint8), (H, W),
    with its capture time on the recording host's CLOCK_MONOTONIC (ns)."""

    t_capture_ns: int
    depth_m: np.ndarray
    gray_u8: np.ndarray


@dataclass(frozen=True)
class LoggedStep:
    """A recorded policy step: what it was computed from and what the model returned.

    ``pos_enu_m``/``goal_enu_m`` local ENU (m), ``quat_enu_flu`` (w, x, y, z), body FLU velocity
    (m/s) and angular rate (rad/s); ``hidden_epoch`` = GRU resets before the step; ``observation``
    (79,) = state (15) + latent (64); ``action_raw`` and ``action_clipped`` (3,).
    """

    frame_seq: int
    t_capture_ns: int
    hidden_epoch: int
    pos_enu_m: np.ndarray
    quat_enu_flu: np.ndarray
    vel_body_flu_m_s: np.ndarray
    angvel_body_flu_rad_s: np.ndarray
    goal_enu_m: np.ndarray
    observation: np.ndarray
    action_raw: np.ndarray
    action_clipped: np.ndarray


class FlightLogReader:
    """Streams one flight log; see the module docstring."""

    def __init__(self, path: str | Path) -> None:
        """Check that ``path`` is an MCAP file; raise :class:`ReplayError` if it is not."""
        self.path = Path(path)
        try:
            with open(self.path, "rb") as f:
                head = f.read(len(MCAP_MAGIC))
        except OSError as err:
            raise ReplayError(f"cannot read flight log {self.path}: {err.strerror or err}") from err
        if head != MCAP_MAGIC:
            raise ReplayError(
                f"{self.path} is not an MCAP file (it starts with {head!r}, not the MCAP magic): "
                "pass a flight log written by cmnav (cmnav fly / cmnav sitl write LOG_DIR/*.mcap)"
            )
        self.metadata: dict[str, str] = {}
        self.topics: set[str] = set()
        self.stopped_early: str | None = None  # why the stream ended before the MCAP footer, e.g. "ends early at byte N, ..."
        self.offset_ns = 0

    def records(self, topics: tuple[str, ...]) -> Iterator[LoggedFrame | LoggedStep]:
        """Frames (if ``topics`` has the camera topics) and steps (if it has the policy topics), in
        the order they were written.  Raises :class:`ReplayError` when the file is not a cmnav
        flight log; a cut or damaged end only stops the iteration (see :attr:`stopped_early`)."""
        depth_pending: dict[int, np.ndarray] = {}
        observation_pending: dict[tuple[int, int], dict] = {}
        for topic, log_time, decoded in self.messages(topics):
            item = self._assemble(topic, log_time, decoded, depth_pending, observation_pending)
            if item is not None:
                yield item

    def messages(self, topics: tuple[str, ...]) -> Iterator[tuple[str, int, Any]]:
        """Every message on ``topics`` as ``(topic, log_time_ns, decoded)`` in the order written:
        JSON channels as dicts, image channels as foxglove ``RawImage`` protobufs; ``log_time_ns``
        is Unix-epoch ns (subtract :attr:`offset_ns` for the recording host's monotonic clock).
        Errors as :meth:`records`."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        decoders: dict[int, Callable[[bytes], Any]] = {}
        with open(self.path, "rb") as f:
            stream = StreamReader(f, validate_crcs=True, record_size_limit=MAX_RECORD_BYTES).records
            while True:
                try:
                    record = next(stream)
                except StopIteration:
                    return
                except InvalidMagic as err:  # the closing magic after the footer
                    raise ReplayError(f"{self.path} ends in bytes that are not the MCAP magic ({err}): the file is damaged") from err
                except _CUT as err:
                    self._stop(f"ends early at byte {f.tell()}, cut short ({_describe(err)})")
                    return
                except _DAMAGED as err:
                    self._stop(f"has damaged data near byte {f.tell()} ({_describe(err)})")
                    return
                if isinstance(record, Metadata) and record.name == METADATA_NAME:
                    self._set_metadata(dict(record.metadata))
                elif isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                    self.topics.add(record.topic)
                elif isinstance(record, Message):
                    if not self.metadata:
                        raise ReplayError(
                            f"{self.path} has no '{METADATA_NAME}' metadata record before its first message: it is "
                            "an MCAP file but not a flight log written by cmnav's recorder"
                        )
                    channel = channels.get(record.channel_id)
                    if channel is None or channel.topic not in topics:
                        continue
                    if record.channel_id not in decoders:
                        decoders[record.channel_id] = self._decoder(channel, schemas.get(channel.schema_id))
                    yield channel.topic, record.log_time, self._decode(decoders[record.channel_id], channel, record)

    def check_topics(self, required: tuple[str, ...], why: str) -> None:
        """After :meth:`records`: raise :class:`ReplayError` naming the ``required`` topics the log lacks."""
        if not self.metadata:
            raise ReplayError(
                f"{self.path} has no '{METADATA_NAME}' metadata record"
                + (f" ({self.stopped_early})" if self.stopped_early else "")
                + ": it is not a flight log written by cmnav's recorder, or it was cut before anything was written"
            )
        missing = [t for t in required if t not in self.topics]
        if missing:
            where = f"; the log {self.stopped_early}" if self.stopped_early else ""
            raise ReplayError(f"{self.path} lacks the channel(s) {', '.join(missing)} ({why}){where}")

    def image(self, raw: Any, topic: str) -> np.ndarray:
        """A camera message from :meth:`messages` as an (H, W) array: depth float32 metres
        (``/camera/depth``), gray uint8 (``/camera/gray``); :class:`ReplayError` for another layout."""
        if topic == TOPIC_DEPTH:
            return self._image(raw, "32FC1", np.dtype("<f4"), topic)
        return self._image(raw, "mono8", np.dtype(np.uint8), topic)

    # ------------------------------------------------------------------ internals

    def _stop(self, why: str) -> None:
        self.stopped_early = why
        log.warning("%s %s; using what came before", self.path, why)

    def _set_metadata(self, metadata: dict[str, str]) -> None:
        version = metadata.get("contract_version")
        if version != CONTRACT_VERSION:
            raise ReplayError(
                f"{self.path} was recorded under contract version {version!r}, this cmnav has {CONTRACT_VERSION!r}: "
                "replay it with the cmnav version that recorded it"
            )
        try:
            self.offset_ns = int(metadata["monotonic_to_unix_offset_ns"])
        except (KeyError, ValueError) as err:
            raise ReplayError(f"{self.path}: the '{METADATA_NAME}' metadata lacks a valid monotonic_to_unix_offset_ns ({err})") from err
        self.metadata = metadata

    def _decoder(self, channel: Channel, schema: Schema | None) -> Callable[[bytes], Any]:
        if channel.message_encoding == "json":
            return json.loads
        if channel.message_encoding == "protobuf" and schema is not None:
            decoder = ProtobufDecoderFactory().decoder_for(channel.message_encoding, schema)
            if decoder is not None:
                return decoder
        raise ReplayError(
            f"{self.path}: channel {channel.topic} has encoding {channel.message_encoding!r} with schema "
            f"{schema.name if schema else None!r}, not what cmnav's recorder writes: the log is not from this cmnav"
        )

    def _decode(self, decoder: Callable[[bytes], Any], channel: Channel, message: Message) -> Any:
        try:
            return decoder(message.data)
        except (ValueError, TypeError) as err:  # json.JSONDecodeError and protobuf's DecodeError are ValueErrors
            raise ReplayError(f"{self.path}: a message on {channel.topic} does not decode ({err}): the log is damaged") from err

    def _assemble(
        self,
        topic: str,
        log_time: int,
        decoded: Any,
        depth_pending: dict[int, np.ndarray],
        observation_pending: dict[tuple[int, int], dict],
    ) -> LoggedFrame | LoggedStep | None:
        """Pair depth with gray (same log time) and observation with action (same frame)."""
        if topic == TOPIC_DEPTH:
            depth_pending.clear()  # the recorder writes depth then gray: an unpaired older depth is a dropped gray
            depth_pending[log_time] = self._image(decoded, "32FC1", np.dtype("<f4"), topic)
            return None
        if topic == TOPIC_GRAY:
            depth = depth_pending.pop(log_time, None)
            if depth is None:
                return None
            gray = self._image(decoded, "mono8", np.dtype(np.uint8), topic)
            if gray.shape != depth.shape:
                raise ReplayError(f"{self.path}: gray {gray.shape} and depth {depth.shape} of one frame differ in size: the log is damaged")
            return LoggedFrame(t_capture_ns=log_time - self.offset_ns, depth_m=depth, gray_u8=gray)
        key = self._step_key(decoded, topic)
        if topic == TOPIC_OBSERVATION:
            observation_pending.clear()
            observation_pending[key] = decoded
            return None
        observation = observation_pending.pop(key, None)
        if observation is None:
            return None
        try:
            return LoggedStep(
                frame_seq=key[1], t_capture_ns=key[0], hidden_epoch=int(observation["hidden_epoch"]),
                pos_enu_m=_array(observation["pos_enu_m"], 3), quat_enu_flu=_array(observation["quat_enu_flu"], 4),
                vel_body_flu_m_s=_array(observation["vel_body_flu_m_s"], 3),
                angvel_body_flu_rad_s=_array(observation["angvel_body_flu_rad_s"], 3),
                goal_enu_m=_array(observation["goal_enu_m"], 3), observation=_array(observation["observation"], None),
                action_raw=_array(decoded["raw"], 3), action_clipped=_array(decoded["clipped"], 3),
            )  # fmt: skip
        except (KeyError, TypeError, ValueError) as err:
            raise ReplayError(
                f"{self.path}: a policy step record lacks or garbles {err}: the log was written by a cmnav that did "
                "not record the step inputs (replay needs a log from this version) or it is damaged"
            ) from err

    def _step_key(self, decoded: Any, topic: str) -> tuple[int, int]:
        try:
            return int(decoded["t_capture_ns"]), int(decoded["frame_seq"])
        except (KeyError, TypeError, ValueError) as err:
            raise ReplayError(f"{self.path}: a message on {topic} lacks t_capture_ns/frame_seq ({err}): not a cmnav step record") from err

    def _image(self, raw: Any, encoding: str, dtype: np.dtype, topic: str) -> np.ndarray:
        if raw.encoding != encoding or raw.step != raw.width * dtype.itemsize or len(raw.data) != raw.step * raw.height:
            raise ReplayError(
                f"{self.path}: {topic} image is {raw.encoding} {raw.width}x{raw.height} (step {raw.step}, "
                f"{len(raw.data)} bytes), expected {encoding} packed rows: not a cmnav camera record"
            )
        return np.frombuffer(raw.data, dtype=dtype).reshape(raw.height, raw.width)


def _describe(err: Exception) -> str:
    return f"{type(err).__name__}: {err}" if str(err) else type(err).__name__


def _array(values: Any, size: int | None) -> np.ndarray:
    """JSON numbers (null = NaN) -> float64 array, checking the length when ``size`` is given."""
    array = np.array([np.nan if v is None else float(v) for v in values], dtype=np.float64)
    if size is not None and array.shape != (size,):
        raise ValueError(f"{size} values expected, got {array.shape[0]}")
    return array
