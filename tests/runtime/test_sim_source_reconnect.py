"""The sim camera source re-opens a link that was delivering frames at once (a torn frame or a
dropped connection costs about a frame period, not ``reconnect_delay_s`` more), and backs off on
a peer that fails before its first frame."""

import asyncio

from runtime.camera.sim_source import SimCameraSource
from runtime.camera.sim_wire import encode_frame
from tests.runtime.test_sim_source import FakeVehicleCamera, _frame

LONG_DELAY_S = 3600.0  # a reconnect that waited for it would time the test out
WAIT_S = 10.0


def test_a_link_that_delivered_frames_is_reopened_without_the_delay():
    async def main():
        torn = encode_frame(_frame(1)) + encode_frame(_frame(2))[:100]  # a frame, then a torn one
        server = FakeVehicleCamera([[torn, b"not a frame header at all, 32 bytes+"], [encode_frame(_frame(7)), b""]])
        port = await server.start()
        source = SimCameraSource(port, reconnect_delay_s=LONG_DELAY_S)
        await source.start()
        try:
            async def seq_7():
                while source.latest.latest() is None or source.latest.latest().value.seq != 7:
                    await asyncio.sleep(0.01)

            await asyncio.wait_for(seq_7(), WAIT_S)
            assert source.stats.connects == 2 and source.stats.disconnects == 1
        finally:
            await source.close()
            await server.stop()

    asyncio.run(main())


def test_a_peer_that_fails_before_its_first_frame_is_retried_only_after_the_delay():
    async def main():
        server = FakeVehicleCamera([[b"garbage that is not a frame header!!"]])
        port = await server.start()
        source = SimCameraSource(port, reconnect_delay_s=LONG_DELAY_S)
        await source.start()
        try:
            while source.stats.decode_errors == 0:
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.3)  # a spinning source would have reconnected many times by now
            assert (source.stats.connects, server.connections) == (1, 1)
        finally:
            await source.close()
            await server.stop()

    asyncio.run(main())
