"""The SITL vehicle's camera link, read the way the runtime's ``sim`` source reads it: decodable
frames of the contract's sim size, a depth that matches the room, a client that replaces
another, and the served frames counted in the trace."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from runtime.camera.sim_wire import HEADER, decode_header, decode_payload, payload_size
from runtime.contract.constants import SIM_CAMERA_HEIGHT_PX, SIM_CAMERA_WIDTH_PX
from sim.camera import CameraModel

pytestmark = pytest.mark.timeout(60)


def _read_exactly(sock: socket.socket, n: int) -> bytes:
    chunks, remaining = [], n
    while remaining:
        chunk = sock.recv(remaining)
        if not chunk:
            raise EOFError("camera server closed the connection")
        chunks.append(chunk)
        remaining -= len(chunk)
    return b"".join(chunks)


def _read_frame(sock: socket.socket):
    seq, t_ns, width, height, meta_len = decode_header(_read_exactly(sock, HEADER.size))
    return decode_payload(seq, t_ns, width, height, _read_exactly(sock, payload_size(width, height, meta_len)))


def test_frames_depth_and_reconnect(launch_sitl):
    sitl = launch_sitl(level=0, seed=5)
    frames = []
    with socket.create_connection(("127.0.0.1", sitl.camera_port), timeout=5.0) as first:
        t_end = time.monotonic() + 2.0
        while time.monotonic() < t_end:
            frames.append(_read_frame(first))
        rate_hz = (len(frames) - 1) / ((frames[-1].t_capture_ns - frames[0].t_capture_ns) * 1e-9)
        print(f"camera: {len(frames)} frames in 2 s, {rate_hz:.1f} Hz by capture time")
        assert len(frames) >= 10
        seqs = [f.seq for f in frames]
        assert seqs == sorted(set(seqs))
        assert all(b.t_capture_ns > a.t_capture_ns for a, b in zip(frames, frames[1:]))
        assert frames[-1].t_capture_ns <= time.monotonic_ns()

        frame = frames[-1]
        assert frame.depth_m.shape == frame.gray_u8.shape == (SIM_CAMERA_HEIGHT_PX, SIM_CAMERA_WIDTH_PX)
        assert frame.depth_m.dtype == np.float32 and frame.gray_u8.dtype == np.uint8
        assert frame.meta == {"invalid_depth_frac": 0.0}
        assert np.all(np.isfinite(frame.depth_m)) and frame.depth_m.min() > 0.05
        assert frame.gray_u8.std() > 5.0  # textured, not flat gray
        # Landed at home facing +x in an empty room: the optical axis meets the far wall x = L.
        room_length_m = sitl.episode["room_size_m"][0]
        camera_x_m = sitl.episode["home_enu_m"][0] + CameraModel().mount_offset_body_flu_m[0]
        centre = frame.depth_m[SIM_CAMERA_HEIGHT_PX // 2 - 1 : SIM_CAMERA_HEIGHT_PX // 2 + 1,
                               SIM_CAMERA_WIDTH_PX // 2 - 1 : SIM_CAMERA_WIDTH_PX // 2 + 1]  # fmt: skip
        assert centre == pytest.approx(room_length_m - camera_x_m, abs=0.05)

        # A second client replaces the first, which is closed.
        with socket.create_connection(("127.0.0.1", sitl.camera_port), timeout=5.0) as second:
            newer = _read_frame(second)
            assert newer.seq >= frames[-1].seq  # the newest frame at once, then new ones
            with pytest.raises((EOFError, ConnectionResetError)):
                for _ in range(100):
                    _read_frame(first)
            frames.append(newer)

    assert sitl.stop() == 0, sitl.log_tail()
    trace = sitl.trace()
    assert trace["frames_served"] >= len(frames)
    assert trace["invalid_depth_frac"] == [0.0] * trace["frames_served"]
