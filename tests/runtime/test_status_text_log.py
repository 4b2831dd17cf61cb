"""The autopilot's STATUSTEXTs in the flight log (/vehicle/status_text)."""

import json
import time

from mavsdk.asyncio.plugins.telemetry import StatusText as MavsdkStatusText
from mavsdk.asyncio.plugins.telemetry import StatusTextType
from mcap.reader import make_reader

from runtime.config import RecorderConfig
from runtime.log.topics import TOPIC_STATUS_TEXT
from runtime.log.recorder import Recorder
from runtime.state import StatusText
from runtime.vehicle import Vehicle


def test_status_texts_read_back_with_their_receive_times(tmp_path):
    path = tmp_path / "flight.mcap"
    rec = Recorder(path, RecorderConfig(flush_period_s=0.2))
    t0 = time.monotonic_ns()
    texts = [StatusText(1, t0, "INFO", "Takeoff complete, holding"), StatusText(2, t0 + 5_000_000, "CRITICAL", "collision: obstacle 1")]
    for text in texts:
        rec.log_status_text(text)
    rec.close()
    with open(path, "rb") as f:
        reader = make_reader(f)
        offset = int({m.name: m.metadata for m in reader.iter_metadata()}["cmnav"]["monotonic_to_unix_offset_ns"])
        read = [(m.log_time, json.loads(m.data)) for _, _, m in reader.iter_messages(topics=[TOPIC_STATUS_TEXT])]
    assert [m for _, m in read] == [{"t_ns": t.t_ns, "seq": t.seq, "severity": t.severity, "text": t.text} for t in texts]
    assert [log_time - offset for log_time, _ in read] == [t.t_ns for t in texts]


def test_vehicle_keeps_mavsdk_status_texts_with_mavlink_severity_names():
    vehicle = Vehicle()
    for kind, text in ((StatusTextType.INFO, "Armed by external command"), (StatusTextType.CRITICAL, "collision: wall x=0")):
        vehicle._fields.update(vehicle._status_text_fields(MavsdkStatusText(kind, text)))
    kept = vehicle.state().status_texts
    assert [(t.seq, t.severity, t.text, t.is_fault) for t in kept] == [
        (1, "INFO", "Armed by external command", False), (2, "CRITICAL", "collision: wall x=0", True)]  # fmt: skip
    assert kept[0].t_ns <= kept[1].t_ns
