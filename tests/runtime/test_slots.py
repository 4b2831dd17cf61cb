import asyncio

import pytest

from runtime.slots import LatestSlot


def test_latest_value_stamp_and_age():
    now = [1_000]
    slot: LatestSlot[str] = LatestSlot("x", clock_ns=lambda: now[0])
    assert slot.latest() is None and slot.age_ns() is None
    first = slot.put("a")
    assert (first.value, first.t_ns, first.seq) == ("a", 1_000, 1)
    slot.put("b", t_ns=1_500)
    now[0] = 2_000
    assert slot.latest().value == "b" and slot.latest().seq == 2
    assert slot.age_ns() == 500 and slot.age_ns(now_ns=1_600) == 100


def test_slow_reader_skips_to_newest():
    async def main():
        slot: LatestSlot[int] = LatestSlot("n")
        for i in range(5):
            slot.put(i)
        got = await slot.wait_newer(0, timeout_s=1.0)
        assert got.value == 4 and got.seq == 5
        return got

    asyncio.run(main())


def test_wait_newer_wakes_on_put_and_times_out():
    async def main():
        slot: LatestSlot[int] = LatestSlot("n")
        slot.put(1)
        waiter = asyncio.create_task(slot.wait_newer(1, timeout_s=2.0))
        await asyncio.sleep(0)
        assert not waiter.done()
        slot.put(2)
        assert (await waiter).value == 2
        with pytest.raises(asyncio.TimeoutError):
            await slot.wait_newer(2, timeout_s=0.01)

    asyncio.run(main())


def test_a_reader_cancelled_as_a_value_arrives_is_cancelled():
    """The policy task waits for frames this way: a stop that comes with a frame must stop it (on
    Python 3.11 ``asyncio.wait_for`` lost that cancellation and the task flew on)."""

    async def main():
        slot: LatestSlot[int] = LatestSlot("frames")
        cancelled = 0
        for spins in range(6):  # the cancel at each point of the value's hand-over, until the reader has it
            reader = asyncio.create_task(slot.wait_newer(slot.latest().seq if slot.latest() else 0, timeout_s=5.0))
            await asyncio.sleep(0)
            slot.put(spins)
            for _ in range(spins):
                await asyncio.sleep(0)
            if reader.cancel():  # not yet finished: the cancellation must stop it
                cancelled += 1
                with pytest.raises(asyncio.CancelledError):
                    await reader
            else:
                assert reader.result().value == spins
        assert 0 < cancelled < 6

    asyncio.run(main())
