"""A SITL world that follows an external autopilot reports a contact in the frame meta; the
flight loop ends the episode on it as on any trip: hover at once, Hold after the grace period."""

import asyncio
import time

import numpy as np
import pytest

from runtime.camera import Frame
from runtime.contract import CONTROL_PERIOD_S, HOVER
from tests.runtime.test_flight_loop import START, FakeCamera, _fly


class ContactCamera(FakeCamera):
    """Frames whose meta reports a contact from ``contact_after_s`` on (as sim.follower sends them)."""

    def __init__(self, contact_after_s: float):
        super().__init__()
        self.contact_after_s = contact_after_s

    async def frames(self):
        t0 = time.monotonic()
        seq = 0
        while True:
            seq += 1
            meta = {"invalid_depth_frac": 0.0}
            if time.monotonic() - t0 >= self.contact_after_s:
                meta["contact"] = {"t_s": t0, "pos_enu_m": [3.0, 1.0, 1.5], "what": "obstacle 2"}
            depth = np.full((120, 212), 3.0, np.float32)
            yield Frame(time.monotonic_ns(), depth, np.full((120, 212), 128, np.uint8), seq, meta)
            await asyncio.sleep(CONTROL_PERIOD_S)


def test_contact_reported_by_the_world_trips_hover_then_hold(goal_seeker):
    goal = START + np.array([15.0, 0.0, 0.0])  # never reached
    result, vehicle = asyncio.run(_fly(goal_seeker, goal, 20.0, camera=ContactCamera(contact_after_s=0.8)))
    assert result.outcome == "aborted" and result.abort_reason == "sim_contact"
    (trip,) = result.watchdog_trips
    assert trip["response"] == "hover_then_hold" and "obstacle 2" in trip["detail"]
    assert trip["hold_t_s"] == pytest.approx(trip["t_s"] + 0.3, abs=0.1)
    assert vehicle.setpoints[-1] == HOVER and vehicle.holds == 1
    assert result.steps > 3  # it flew on the frames before the contact
