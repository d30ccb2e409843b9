"""Frames handed over inside one process: a bounded, thread-safe queue that drops the oldest."""

from __future__ import annotations

import threading
from collections import deque

from protocol.frames import Frame

__all__ = ["InProcessSource"]


class InProcessSource:
    """A frame source fed directly in the same process (fast tests, ``planer hil`` in-process).

    Thread-safe. When full, the oldest frame is dropped (a camera overwrites its buffer).

    Parameters
    ----------
    maxlen : int
        Frames buffered at most.

    Attributes
    ----------
    dropped : int
        Frames lost because the buffer was full.
    """

    def __init__(self, maxlen: int = 64) -> None:
        if isinstance(maxlen, bool) or not isinstance(maxlen, int) or maxlen < 1:
            raise ValueError(f"maxlen must be an integer >= 1, got {maxlen!r}")
        self._q: deque[Frame] = deque(maxlen=maxlen)
        self._lock = threading.Lock()
        self.dropped = 0

    def put(self, frame: Frame) -> None:
        """Hand a frame over."""
        with self._lock:
            if len(self._q) == self._q.maxlen:
                self.dropped += 1
            self._q.append(frame)

    write = put  # the same call as SpoolWriter.write, so the runner takes either sink

    def poll(self) -> Frame | None:
        """The oldest buffered frame, or ``None`` (never blocks)."""
        with self._lock:
            return self._q.popleft() if self._q else None

    def __len__(self) -> int:
        return len(self._q)
