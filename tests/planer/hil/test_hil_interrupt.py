"""One Ctrl-C ends a HIL run even when ``asyncio.wait_for`` swallowed its cancellation."""

from __future__ import annotations

import asyncio
import signal
import sys

import pytest

from planer.hil.interrupt import raise_if_cancel_lost

STEPS = 50


async def _a_run(fut: asyncio.Future, seen: list) -> str:
    """A run's loop that awaits ``fut`` through ``wait_for`` (as the service awaits the PLC)."""
    seen.append(await asyncio.wait_for(fut, 10.0))  # the cancellation may be lost here
    for _ in range(STEPS):
        raise_if_cancel_lost()
        await asyncio.sleep(0)
    return "went on"


def test_a_cancellation_lost_in_wait_for_ends_the_run_at_its_next_step():
    async def main():
        loop = asyncio.get_running_loop()
        fut = loop.create_future()
        seen: list = []
        task = asyncio.create_task(_a_run(fut, seen))
        await asyncio.sleep(0)  # the task waits in wait_for
        fut.set_result(1)  # the awaited request answers ...
        task.cancel()  # ... in the instant Ctrl-C cancels the task
        with pytest.raises(asyncio.CancelledError):
            await task
        return seen

    seen = asyncio.run(main())
    if sys.version_info < (3, 12):  # 3.11's wait_for returned the answer (the cancel was lost)
        assert seen == [1]


def test_one_ctrl_c_ends_asyncio_run_in_keyboard_interrupt():
    """asyncio.run's own Ctrl-C: SIGINT cancels the main task; a lost cancel still ends it."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # asyncio.run's handler
    try:
        async def main():
            loop = asyncio.get_running_loop()
            fut = loop.create_future()

            def ctrl_c() -> None:
                fut.set_result(1)
                signal.raise_signal(signal.SIGINT)

            loop.call_soon(ctrl_c)
            return await _a_run(fut, [])

        with pytest.raises(KeyboardInterrupt):
            asyncio.run(main())
    finally:
        signal.signal(signal.SIGINT, before)


def test_a_task_not_cancelled_runs_on_and_outside_a_task_nothing_is_raised():
    raise_if_cancel_lost()  # no event loop

    async def main():
        fut = asyncio.get_running_loop().create_future()
        fut.set_result(2)
        seen: list = []
        assert await _a_run(fut, seen) == "went on" and seen == [2]

    asyncio.run(main())
