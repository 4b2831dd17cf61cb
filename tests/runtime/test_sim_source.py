import asyncio
import time

import numpy as np

from runtime.camera import CameraSource, Frame
from runtime.camera.sim_source import SimCameraSource
from runtime.camera.sim_wire import encode_frame


def _frame(seq: int) -> Frame:
    depth = np.full((12, 20), 1.0 + seq, np.float32)
    gray = np.full((12, 20), seq % 256, np.uint8)
    return Frame(t_capture_ns=1_000 + seq, depth_m=depth, gray_u8=gray, seq=seq, meta={"seq": seq})


class FakeVehicleCamera:
    """A TCP server like the SITL vehicle's camera link; each connection runs the next script."""

    def __init__(self, scripts):
        self.scripts = list(scripts)
        self.connections = 0
        self.server: asyncio.base_events.Server | None = None

    async def start(self) -> int:
        self.server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        return self.server.sockets[0].getsockname()[1]

    async def _serve(self, reader, writer):
        script = self.scripts[min(self.connections, len(self.scripts) - 1)]
        self.connections += 1
        try:
            for chunk in script:
                writer.write(chunk)
                await writer.drain()
                await asyncio.sleep(0.005)
            if script and script[-1] == b"":  # keep the link open
                await asyncio.sleep(30)
        finally:
            writer.close()

    async def stop(self):
        self.server.close()


async def _collect(source: SimCameraSource, n: int, timeout_s: float = 5.0) -> list[Frame]:
    got: list[Frame] = []

    async def run():
        async for frame in source.frames():
            got.append(frame)
            if len(got) >= n:
                return

    await asyncio.wait_for(run(), timeout_s)
    return got


def test_is_a_camera_source():
    assert isinstance(SimCameraSource(1), CameraSource)


def test_reads_frames_and_keeps_latest():
    async def main():
        server = FakeVehicleCamera([[encode_frame(_frame(i)) for i in range(1, 6)] + [b""]])
        port = await server.start()
        source = SimCameraSource(port, reconnect_delay_s=0.02)
        t_before_ns = time.monotonic_ns()
        await source.start()
        try:
            first = await _collect(source, 1)
            assert first[0].depth_m.shape == (12, 20) and first[0].meta["seq"] == first[0].seq
            await asyncio.sleep(0.2)  # the rest arrives while nobody reads
            latest = source.latest.latest().value
            assert latest.seq == 5 and latest.t_capture_ns == 1_005
            # the receipt is stamped on this host's clock when the frame came off the link
            assert t_before_ns < first[0].t_received_ns <= latest.t_received_ns <= time.monotonic_ns()
            assert latest.t_grab_ns == latest.t_received_ns
            assert float(latest.depth_m[0, 0]) == 6.0 and int(latest.gray_u8[0, 0]) == 5
            assert source.stats.frames == 5 and source.stats.decode_errors == 0
        finally:
            await source.close()
            await server.stop()

    asyncio.run(main())


def test_garbage_is_counted_and_link_reopened():
    async def main():
        server = FakeVehicleCamera(
            [
                [encode_frame(_frame(1)), b"garbage bytes that are not a frame header!!"],
                [encode_frame(_frame(7)), b""],
            ]
        )
        port = await server.start()
        source = SimCameraSource(port, reconnect_delay_s=0.02)
        await source.start()
        try:
            await asyncio.wait_for(_wait_for_seq(source, 7), 5.0)
            assert source.stats.decode_errors == 1
            assert "bad magic" in source.stats.last_error
            assert source.stats.connects == 2
        finally:
            await source.close()
            await server.stop()

    asyncio.run(main())


def test_reconnects_after_server_disconnect_and_before_server_exists():
    async def main():
        server = FakeVehicleCamera([[encode_frame(_frame(1))], [encode_frame(_frame(2)), b""]])
        port = await server.start()
        await server.stop()  # nothing listens yet: the source keeps trying
        server.server = None
        source = SimCameraSource(port, reconnect_delay_s=0.02)
        await source.start()
        try:
            await asyncio.sleep(0.1)
            assert source.stats.connects == 0
            server.server = await asyncio.start_server(server._serve, "127.0.0.1", port)
            await asyncio.wait_for(_wait_for_seq(source, 2), 5.0)
            assert source.stats.connects == 2 and source.stats.disconnects >= 1
            assert source.stats.decode_errors == 0
        finally:
            await source.close()
            await server.stop()

    asyncio.run(main())


def test_truncated_frame_is_a_dropped_link_not_a_crash():
    async def main():
        whole = encode_frame(_frame(3))
        server = FakeVehicleCamera([[whole[: len(whole) // 2]], [encode_frame(_frame(4)), b""]])
        port = await server.start()
        source = SimCameraSource(port, reconnect_delay_s=0.02)
        await source.start()
        try:
            await asyncio.wait_for(_wait_for_seq(source, 4), 5.0)
            assert source.stats.frames == 1 and "dropped" in source.stats.last_error
        finally:
            await source.close()
            await server.stop()

    asyncio.run(main())


async def _wait_for_seq(source: SimCameraSource, seq: int) -> None:
    async for frame in source.frames():
        if frame.seq == seq:
            return


def test_silent_link_is_reopened():
    async def main():
        server = FakeVehicleCamera([[encode_frame(_frame(1)), b""], [encode_frame(_frame(2)), b""]])
        port = await server.start()
        source = SimCameraSource(port, reconnect_delay_s=0.02, read_timeout_s=0.2)
        await source.start()
        try:
            await asyncio.wait_for(_wait_for_seq(source, 2), 5.0)
            assert source.stats.connects == 2 and "silent" in source.stats.last_error
        finally:
            await source.close()
            await server.stop()

    asyncio.run(main())
