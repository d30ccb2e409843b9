"""The hand-off from the service to the servers' process: bounded, never waiting.

Three parts, each on its own side:

- :func:`follow` runs on the service's event loop: every ``period_s`` it takes the service's
  ``status()``, its new events and its new results (references, no conversion) and puts them
  in a :class:`Mailbox`. That is all the loop pays for the servers.
- :class:`Mailbox` holds at most ``capacity`` items; a full mailbox drops its oldest item
  (counted in :attr:`Mailbox.dropped`). Putting never waits on the consumer.
- :class:`Translator`, on a thread of its own, turns a batch of items into one plain message
  for the servers' process: the operator page's JSON (:mod:`controller.web.live`) and the OPC
  UA values and events (:class:`controller.opcua.view.MachineView`, pure).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

from controller.opcua.view import MachineView
from controller.quality.schema import QualityClass
from controller.web.live import event_json, result_json, status_json

__all__ = ["Mailbox", "Translator", "follow", "follow_once"]

_log = logging.getLogger(__name__)

_FOLLOW_ERRORS = (AttributeError, TypeError, ValueError, KeyError, IndexError)


class Mailbox:
    """A bounded, thread-safe queue that drops its oldest item when full.

    Parameters
    ----------
    capacity : int
        Items held at most.
    """

    def __init__(self, capacity: int = 512) -> None:
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f"capacity must be an integer >= 1, got {capacity!r}")
        self._items: deque[tuple[str, Any]] = deque(maxlen=capacity)
        self._ready = threading.Condition(threading.Lock())
        self.dropped = 0
        """Items dropped because the consumer was behind."""
        self.put_count = 0
        """Items put in all."""

    def put(self, kind: str, item: Any) -> None:
        """Add an item; never waits for the consumer (drops the oldest when full)."""
        with self._ready:
            if len(self._items) == self._items.maxlen:
                self.dropped += 1
            self._items.append((kind, item))
            self.put_count += 1
            self._ready.notify()

    def take(self, timeout_s: float) -> list[tuple[str, Any]]:
        """Everything held, waiting at most ``timeout_s`` for the first item (``[]``: none)."""
        with self._ready:
            if not self._items:
                self._ready.wait(timeout_s)
            out = list(self._items)
            self._items.clear()
            return out

    def __len__(self) -> int:
        with self._ready:
            return len(self._items)


def follow_once(service: Any, seen: dict[str, Any], box: Mailbox) -> None:
    """Put what ``service`` has new since the last call into ``box`` (references only).

    ``seen`` keeps the positions in its ``events`` and ``results`` lists (a new service
    object starts over). Items: ``("service", None)`` for a new service,
    ``("counts_per_mm", float)`` once, ``("event", ServiceEvent)``, ``("result",
    FrameResult)``, ``("status", ServiceStatus)``.
    """
    if seen.get("service") is not service:
        seen.clear()
        seen.update(service=service, events=0, results=0, last=None, cpm=False)
        box.put("service", getattr(service, "quality_class", None))
    if not seen["cpm"]:
        snap = getattr(getattr(service, "plc", None), "last", None)
        cpm = getattr(snap, "counts_per_mm", None)
        if cpm is not None:
            box.put("counts_per_mm", float(cpm))
            seen["cpm"] = True
    events = getattr(service, "events", None) or []
    for e in events[seen["events"]:]:
        box.put("event", e)
    seen["events"] = len(events)
    results = getattr(service, "results", None)
    if results is not None and getattr(service, "keep_results", False):
        for r in results[seen["results"]:]:
            box.put("result", r)
        seen["results"] = len(results)
    else:  # the service keeps no list: its newest result
        last = getattr(getattr(service, "pipeline", None), "last", None)
        if last is not None and last is not seen["last"]:
            box.put("result", last)
        seen["last"] = last
    box.put("status", service.status())


async def follow(get_service: Callable[[], Any], box: Mailbox, *, period_s: float = 0.1) -> None:
    """Follow whatever ``get_service()`` returns (``None`` until there is one) into ``box``.

    Runs on the service's event loop until cancelled; a display's trouble is logged and never
    raised into the service.
    """
    if not period_s > 0:
        raise ValueError(f"period_s must be > 0, got {period_s}")
    seen: dict[str, Any] = {}
    while True:
        service = get_service()
        if service is not None:
            try:
                follow_once(service, seen, box)
            except _FOLLOW_ERRORS:
                _log.exception("servers: following the service failed")  # retried next period
        await asyncio.sleep(period_s)


class Translator:
    """Batches of mailbox items as messages for the servers' process (plain, picklable).

    Parameters
    ----------
    web : bool
        Compute the operator page's JSON.
    opcua : bool
        Compute the OPC UA values and events.
    quality_class : QualityClass or None
        The class OPC UA judges each measurement against (``Passed``).
    """

    def __init__(self, *, web: bool, opcua: bool,
                 quality_class: QualityClass | None = None) -> None:
        self.web = web
        self.view = MachineView(quality_class=quality_class) if opcua else None
        self._sent_status: dict[str, Any] | None = None

    def message(self, items: list[tuple[str, Any]]) -> dict[str, Any]:
        """One message for the items: ``{"web": {...}, "opcua": {...}}`` (parts as asked).

        ``web``: ``status`` (the newest :func:`status_json`, ``None`` when unchanged),
        ``events``, ``results`` (JSON lists), ``counts_per_mm`` (or ``None``), ``service_qc``
        (the service's quality class when a new service appeared, else absent). ``opcua``:
        ``values`` (:meth:`MachineView.all_values`, ``None`` when nothing came that changes
        them) and ``events`` (``WwEvent`` list).
        """
        web: dict[str, Any] = {"status": None, "events": [], "results": [],
                               "counts_per_mm": None}
        ww_events: list[Any] = []
        touched = False
        status = None
        for kind, item in items:
            if kind == "status":
                status = item  # the newest snapshot is enough for the page ...
                if self.view is not None:
                    self.view.update(item)  # ... OPC UA integrates every one
                    touched = True
            elif kind == "event":
                if self.web:
                    web["events"].append(event_json(item))
                if self.view is not None:
                    ww_events.append(self.view.event(item))
            elif kind == "result":
                if self.web:
                    web["results"].append(result_json(item))
                if self.view is not None:
                    self.view.result(item)
                    touched = True
            elif kind == "counts_per_mm":
                web["counts_per_mm"] = item
            elif kind == "service":
                web["service_qc"] = item
        if self.web and status is not None:
            d = status_json(status)
            if d != self._sent_status:
                web["status"] = self._sent_status = d
        out: dict[str, Any] = {}
        if self.web:
            out["web"] = web
        if self.view is not None:
            out["opcua"] = {"values": self.view.all_values() if touched else None,
                            "events": ww_events}
        return out
