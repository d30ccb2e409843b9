"""One Ctrl-C stops a HIL run: a cancellation lost on its way is raised again.

``asyncio.run`` turns the first Ctrl-C into a cancellation of the main task. Python 3.11's
``asyncio.wait_for`` drops that cancellation when the future it waits for finished in the same
instant (it returns the result instead; CPython gh-86296), and the service awaits its PLC
requests through ``wait_for``: the run would go on, and with ``--http`` serve its end until a
second Ctrl-C. The task still counts the request (``Task.cancelling()``), so the run's loop asks
:func:`raise_if_cancel_lost` at each step and ends as the cancellation would have ended it.
"""

from __future__ import annotations

import asyncio

__all__ = ["raise_if_cancel_lost"]


def raise_if_cancel_lost() -> None:
    """Raise ``CancelledError`` if the running task was cancelled and went on regardless.

    Nothing outside a task (no running loop, or a plain callback). ``asyncio.timeout`` and
    ``TaskGroup`` withdraw their own cancellations (``uncancel``), so a count left over is a
    stop request that was swallowed on its way (see the module's description).

    Raises
    ------
    asyncio.CancelledError
        The task is being cancelled: ``asyncio.run`` then ends in ``KeyboardInterrupt`` when
        the cancellation was its Ctrl-C.
    """
    try:
        task = asyncio.current_task()
    except RuntimeError:  # no running event loop
        return
    if task is not None and task.cancelling():
        raise asyncio.CancelledError("a cancellation lost on its way (Ctrl-C)")
