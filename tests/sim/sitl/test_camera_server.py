"""The camera link server with synthetic frames: decodable frames, newest-only delivery to a
slow client, one client at a time, a busy port named in the error."""

import socket
import time

import numpy as np
import pytest

from runtime.camera.frame import Frame
from runtime.camera.sim_wire import HEADER, decode_header, decode_payload, payload_size
from sim.sitl.camera_server import CameraPortError, FrameServer


def _frame(seq: int) -> Frame:
    depth = np.full((120, 212), 1.0 + seq, np.float32)
    return Frame(time.monotonic_ns(), depth, np.full((120, 212), seq % 256, np.uint8), seq, {"invalid_depth_frac": 0.25})


def _read_exactly(sock: socket.socket, n: int) -> bytes:
    data = bytearray()
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        assert chunk, "server closed the connection"
        data += chunk
    return bytes(data)


def _read(sock: socket.socket) -> Frame:
    seq, t_ns, width, height, meta_len = decode_header(_read_exactly(sock, HEADER.size))
    return decode_payload(seq, t_ns, width, height, _read_exactly(sock, payload_size(width, height, meta_len)))


@pytest.fixture
def server():
    srv = FrameServer(0)
    srv.start()
    try:
        yield srv
    finally:
        srv.close()


def _wait(predicate, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.005)


def test_client_gets_the_newest_frame(server):
    server.publish(_frame(0))
    with socket.create_connection(("127.0.0.1", server.port), timeout=5.0) as client:
        frame = _read(client)
        assert frame.seq == 0 and frame.meta == {"invalid_depth_frac": 0.25}
        np.testing.assert_array_equal(frame.depth_m, 1.0)
        server.publish(_frame(1))
        assert _read(client).seq == 1
    _wait(lambda: len(server.served()) == 2)
    assert [f.invalid_depth_frac for f in server.served()] == [0.25, 0.25]


def test_slow_client_skips_to_the_newest_frame(server):
    server.publish(_frame(0))
    with socket.create_connection(("127.0.0.1", server.port), timeout=5.0) as client:
        for seq in range(1, 200):  # the client reads nothing meanwhile
            server.publish(_frame(seq))
        time.sleep(0.2)
        seqs = [_read(client).seq]
        while seqs[-1] != 199:
            seqs.append(_read(client).seq)
    assert len(seqs) < 10, f"a slow client got a backlog: {seqs}"


def test_a_new_client_replaces_the_old_one(server):
    server.publish(_frame(0))
    with socket.create_connection(("127.0.0.1", server.port), timeout=5.0) as old:
        assert _read(old).seq == 0
        with socket.create_connection(("127.0.0.1", server.port), timeout=5.0) as new:
            assert _read(new).seq == 0
            server.publish(_frame(1))
            assert _read(new).seq == 1
            assert old.recv(1) == b""  # closed by the server


def test_busy_port_is_named(server):
    with pytest.raises(CameraPortError, match=f"camera port 127.0.0.1:{server.port}.*--camera-port"):
        FrameServer(server.port)
