"""EpisodeResult.summary(): the one JSON record of an episode, for `cmnav fly`'s episodes and the
SITL flight's summary alike; its keys are published (scripts and tests read them)."""

import json
import math

from runtime.flight import EpisodeResult

PUBLISHED_KEYS = {
    "outcome", "abort_reason", "time_s", "frames", "frames_received", "missed_deadlines", "bad_frames", "step_ms",
    "stage_ms", "watchdog_trips", "final_distance_m", "frames_rejected", "tracking_error_peak_m_s", "brake", "approach_cap",
}  # fmt: skip


def test_summary_keeps_the_published_keys_and_counts_steps_as_frames():
    result = EpisodeResult(
        outcome="success", abort_reason=None, time_s=4.2, steps=63, frames_received=70, missed_deadlines=1,
        bad_frames=0, step_ms={"p50": 9.0}, stage_ms={}, watchdog_trips=[{"cause": "geofence"}], final_distance_m=0.4,
    )  # fmt: skip
    record = result.summary()
    assert set(record) == PUBLISHED_KEYS
    assert record["frames"] == 63 and record["watchdog_trips"] == [{"cause": "geofence"}]
    assert json.loads(json.dumps(record))["frames"] == 63
    assert math.isclose(record["final_distance_m"], 0.4)
