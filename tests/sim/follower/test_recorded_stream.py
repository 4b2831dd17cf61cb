"""A follower fed a recorded pose stream renders the frames our vehicle's own camera renders at
those poses.

The stream is recorded from our own airframe flying in its room (take-off, forward, turning),
encoded as our vehicle encodes it for MAVLink (``sim.sitl.telemetry``: LOCAL_POSITION_NED and
ATTITUDE_QUATERNION, float32 on the wire), and played over loopback to a real
:class:`WorldFollower` in the same room; each frame it serves on its camera link is compared with
our vehicle's camera feed rendering the recorded pose.
"""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from runtime.camera.sim_wire import HEADER, decode_header, decode_payload, payload_size
from sim.camera import CameraModel
from sim.follower.follower import FollowerConfig, WorldFollower
from sim.sitl.airframe import Airframe
from sim.sitl.camera_feed import CameraFeed
from sim.sitl.flight_tasks import VelocityCommand
from sim.sitl.geodetic import GeodeticHome
from sim.sitl.px4 import HOLD
from sim.sitl.telemetry import AutopilotStatus, Telemetry
from sim.world import make_worlds

pytestmark = pytest.mark.timeout(180)

LOOPBACK = "127.0.0.1"
LEVEL, SEED = 3, 11
DT_S = 0.01


def _record_flight():
    """Our vehicle's poses (Kinematics, room frame) and their MAVLink encoding (bytes)."""
    world = make_worlds(LEVEL, SEED, 1)
    start = world.start_m[0].double().numpy()
    airframe = Airframe(world, start[:2], yaw_enu_rad=0.0)
    t_boot_ns = time.monotonic_ns()
    telemetry = Telemetry(airframe.home_enu_m, GeodeticHome(), t_boot_ns)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    first = airframe.kinematics(t_boot_ns)
    plan = [((0.0, 0.0, 1.0), 0.0, 120), ((1.0, 0.3, 0.0), 0.5, 100), ((0.8, -0.2, -0.2), -0.8, 100)]
    poses = []
    for vel, yaw_rate, steps in plan:
        for i in range(steps):
            assert airframe.step(VelocityCommand(np.array(vel), yaw_rate), DT_S) is None
            if i % 25 == 24:
                poses.append(airframe.kinematics())
    status = AutopilotStatus(False, HOLD, mavlink.MAV_LANDED_STATE_ON_GROUND, True, False)
    head = [telemetry.heartbeat(status), telemetry.sys_status(status), telemetry.home_position(first),
            telemetry.local_position_ned(first), telemetry.attitude_quaternion(first)]  # fmt: skip
    stream = [b"".join(m.pack(mav) for m in (telemetry.local_position_ned(k), telemetry.attitude_quaternion(k))) for k in poses]
    return world, poses, [m.pack(mav) for m in head], stream


def _read_frame(sock: socket.socket):
    def exactly(n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = sock.recv(n - len(data))
            assert chunk, "camera link closed"
            data += chunk
        return data

    seq, t_ns, width, height, meta_len = decode_header(exactly(HEADER.size))
    return decode_payload(seq, t_ns, width, height, exactly(payload_size(width, height, meta_len)))


def _wait(condition, what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.005)


def test_follower_renders_what_our_vehicle_renders_at_the_recorded_poses(tmp_path):
    world, poses, head, stream = _record_flight()
    own_camera = CameraFeed(world, CameraModel(), lambda: poses[0], lambda frame: None, 15.0)
    config = FollowerConfig(LOOPBACK, 0, 0, LEVEL, SEED, tmp_path / "episode.json", tmp_path / "trace.json")
    follower = WorldFollower(config)
    stop = threading.Event()
    thread = threading.Thread(target=follower.run, args=(stop,), daemon=True)
    thread.start()
    autopilot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    autopilot.bind((LOOPBACK, 0))
    camera = None
    try:
        dest = (LOOPBACK, follower.link_port)
        _wait_for_placement = lambda: config.episode_json.exists()  # noqa: E731
        deadline = time.monotonic() + 60.0
        while not _wait_for_placement():  # the autopilot keeps announcing itself until the room is placed
            assert time.monotonic() < deadline and thread.is_alive(), "the follower did not place the room"
            for datagram in head:
                autopilot.sendto(datagram, dest)
            time.sleep(0.05)
        episode = json.loads(config.episode_json.read_text())
        np.testing.assert_allclose(episode["placement"]["heading_local_enu_rad"], 0.0, atol=1e-6)
        camera = socket.create_connection((LOOPBACK, follower.camera_port), timeout=10.0)
        compared = 0
        for kin, datagram in zip(poses, stream):
            autopilot.sendto(datagram, dest)
            _wait(lambda: np.allclose(follower.followed.pos_enu_m, kin.pos_enu_m, atol=1e-4), "the followed pose")
            t_followed_ns = time.monotonic_ns()
            frame = _read_frame(camera)
            while frame.t_capture_ns <= t_followed_ns:
                frame = _read_frame(camera)
            own = own_camera.render_frame(kin)
            depth_diff = np.abs(frame.depth_m - own.depth_m)
            assert np.mean(depth_diff > 1e-3) < 0.001, f"pose {compared}: {np.mean(depth_diff > 1e-3):.2%} depth pixels differ"
            assert np.mean(frame.gray_u8 != own.gray_u8) < 0.001
            assert "contact" not in frame.meta
            compared += 1
        assert compared == len(poses) >= 10
        # The stream stops (a dead link): frames at the last pose stop too, and say so in the trace.
        camera.settimeout(1.0)
        deadline = time.monotonic() + 15.0
        while True:
            assert time.monotonic() < deadline, "frames kept coming at a pose that no longer arrives"
            try:
                _read_frame(camera)
            except TimeoutError:
                break
    finally:
        stop.set()
        thread.join(timeout=10.0)
        autopilot.close()
        if camera is not None:
            camera.close()
    trace = json.loads(config.trace_json.read_text())
    assert trace["collision"] is None and trace["pose_stream"]["position_messages"] >= len(poses)
    assert trace["pose_stream"]["frames_withheld_stale_pose"] > 0
