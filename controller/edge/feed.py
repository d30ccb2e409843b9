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
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from controller.opcua.heads_view import MoulderView
from controller.opcua.view import MachineView
from controller.quality.schema import QualityClass
from controller.web.live import event_json, result_json, status_json

__all__ = ["HEAD_KEYS", "Headed", "Mailbox", "Translator", "follow", "follow_once",
           "head_config_json", "head_configs_json", "heads_of"]

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


@dataclass(frozen=True)
class Headed:
    """A mailbox item of one head of a moulder (``item`` as a single service's)."""

    head: str
    item: Any


def heads_of(followed: Any) -> Mapping[str, Any] | None:
    """The heads' services of a moulder composition (``heads``), or ``None`` for one service."""
    heads = getattr(followed, "heads", None)
    return heads if isinstance(heads, Mapping) and heads else None


def _plain(v: Any) -> Any:
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    value = getattr(v, "value", None)  # an enum (Face)
    return value if isinstance(value, str) else str(v)


def head_config_json(hc: Any, name: str | None = None) -> dict[str, Any]:
    """One head's configuration as a plain dict (:data:`HEAD_KEYS`; missing ones ``None``)."""
    d: dict[str, Any] = {"name": str(name if name is not None else hc.name)}
    for key in HEAD_KEYS[1:]:
        d[key] = _plain(getattr(hc, key, None))
    return d


def head_configs_json(followed: Any) -> list[dict[str, Any]]:
    """The heads of a composition as plain dicts (:data:`HEAD_KEYS`), in its order.

    From its ``head_configs``; a head without one gets only its ``name``.
    """
    heads = heads_of(followed) or {}
    configs = {getattr(hc, "name", None): hc for hc in getattr(followed, "head_configs", ())}
    return [head_config_json(configs.get(name), name) for name in heads]


HEAD_KEYS = ("name", "face", "knives", "rpm", "rpm_min", "rpm_max", "target_pitch_mm",
             "position_mm")
"""The keys of :func:`head_configs_json`."""


def follow_once(service: Any, seen: dict[str, Any], box: Mailbox) -> None:
    """Put what ``service`` has new since the last call into ``box`` (references only).

    ``seen`` keeps the positions in its ``events`` and ``results`` lists (a new service
    object starts over). Items: ``("service", None)`` for a new service,
    ``("counts_per_mm", float)`` once, ``("event", ServiceEvent)``, ``("result",
    FrameResult)``, ``("status", ServiceStatus)``.

    A moulder composition (``heads``: name -> Service, ``head_configs``) gives
    ``("heads", [dict, ...])`` (:func:`head_configs_json`) first on every call (the same list
    object while the composition is the same), then each head's items as
    above with the item wrapped in :class:`Headed`, plus ``("plc", Headed(name, {...}))``
    (the head's measured ``spindle_rpm`` and ``knives``) and ``("machine", dict)`` (the feed
    coordinator's ``feed.describe()``) every call.
    """
    heads = heads_of(service)
    if heads is None:
        _follow_one(service, seen, box, None)
        return
    if seen.get("service") is not service:
        seen.clear()
        seen.update(service=service, heads={}, configs=head_configs_json(service))
    box.put("heads", seen["configs"])  # every time: a full mailbox may drop the first
    for name, svc in heads.items():
        _follow_one(svc, seen["heads"].setdefault(name, {}), box, str(name))
    describe = getattr(getattr(service, "feed", None), "describe", None)
    if callable(describe):
        box.put("machine", describe())


def _plc_facts(service: Any) -> dict[str, Any]:
    snap = getattr(getattr(service, "plc", None), "last", None)
    out: dict[str, Any] = {}
    for key in ("spindle_rpm", "knives"):
        try:
            out[key] = float(getattr(snap, key))
        except (AttributeError, KeyError, TypeError, ValueError):
            out[key] = None
    return out


def _follow_one(service: Any, seen: dict[str, Any], box: Mailbox, head: str | None) -> None:
    """One service's new items (wrapped in :class:`Headed` for a moulder's head)."""

    def put(kind: str, item: Any) -> None:
        box.put(kind, item if head is None else Headed(head, item))

    if seen.get("service") is not service:
        seen.clear()
        seen.update(service=service, events=0, results=0, last=None, cpm=False)
        put("service", getattr(service, "quality_class", None))
    if not seen["cpm"]:
        snap = getattr(getattr(service, "plc", None), "last", None)
        cpm = getattr(snap, "counts_per_mm", None)
        if cpm is not None:
            put("counts_per_mm", float(cpm))
            seen["cpm"] = True
    events = getattr(service, "events", None) or []
    for e in events[seen["events"]:]:
        put("event", e)
    seen["events"] = len(events)
    results = getattr(service, "results", None)
    if results is not None and getattr(service, "keep_results", False):
        for r in results[seen["results"]:]:
            put("result", r)
        seen["results"] = len(results)
    else:  # the service keeps no list: its newest result
        last = getattr(getattr(service, "pipeline", None), "last", None)
        if last is not None and last is not seen["last"]:
            put("result", last)
        seen["last"] = last
    if head is not None:
        put("plc", _plc_facts(service))
    put("status", service.status())


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
        self.opcua = opcua
        self.quality_class = quality_class
        self.view = MachineView(quality_class=quality_class) if opcua else None
        self.heads: MoulderView | None = None
        """The moulder's OPC UA view, once a ``("heads", ...)`` item came."""
        self._sent_status: dict[str, Any] | None = None
        self._sent_heads: dict[str, dict[str, Any]] = {}
        self._sent_machine: dict[str, Any] | None = None
        self._heads_list: list[dict[str, Any]] | None = None

    def message(self, items: list[tuple[str, Any]]) -> dict[str, Any]:
        """One message for the items: ``{"web": {...}, "opcua": {...}}`` (parts as asked).

        ``web``: ``status`` (the newest :func:`status_json`, ``None`` when unchanged),
        ``events``, ``results`` (JSON lists), ``counts_per_mm`` (or ``None``), ``service_qc``
        (the service's quality class when a new service appeared, else absent). ``opcua``:
        ``values`` (:meth:`MachineView.all_values`, ``None`` when nothing came that changes
        them) and ``events`` (``WwEvent`` list).

        A moulder's heads (:class:`Headed` items) add to ``web``: ``heads`` (the heads'
        list when they changed: a composition with other heads), ``head_status`` (name ->
        :func:`status_json`, the changed ones), ``head_counts_per_mm``, ``head_qc``,
        ``head_plc`` (name -> measured ``spindle_rpm``, ``knives``), ``machine`` (the
        coordinator's decision, when changed); their events and results carry ``head``. To
        ``opcua``: ``heads`` (the heads' list when they changed) and ``values`` of
        :meth:`MoulderView.all_values`.
        """
        web: dict[str, Any] = {"status": None, "events": [], "results": [],
                               "counts_per_mm": None}
        op: dict[str, Any] = {"events": []}
        touched = False
        status = None
        head_status: dict[str, Any] = {}
        for kind, item in items:
            if isinstance(item, Headed):
                touched |= self._head_item(kind, item.head, item.item, web, op, head_status)
            elif kind == "heads":
                touched |= self._start_heads(item, web, op)
            elif kind == "machine":
                touched |= self._machine(item, web)
            elif kind == "status":
                status = item  # the newest snapshot is enough for the page ...
                if self.view is not None:
                    self.view.update(item)  # ... OPC UA integrates every one
                    touched = True
            elif kind == "event":
                if self.web:
                    web["events"].append(event_json(item))
                if self.view is not None:
                    op["events"].append(self.view.event(item))
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
        if self.web and head_status:
            changed = {h: status_json(s) for h, s in head_status.items()}
            changed = {h: d for h, d in changed.items() if d != self._sent_heads.get(h)}
            self._sent_heads.update(changed)
            if changed:
                web["head_status"] = changed
        out: dict[str, Any] = {}
        if self.web:
            out["web"] = web
        if self.opcua:
            view = self.heads if self.heads is not None else self.view
            op["values"] = view.all_values() if touched and view is not None else None
            out["opcua"] = op
        return out

    def _start_heads(self, heads: list[dict[str, Any]], web: dict[str, Any],
                     op: dict[str, Any]) -> bool:
        """A moulder's heads: new ones (a view per head for OPC UA, the list for both)."""
        if heads == self._heads_list:
            return False
        self._heads_list = heads
        self._sent_heads, self._sent_machine = {}, None
        if self.web:
            web["heads"] = heads
        if self.opcua:
            self.heads = MoulderView(heads, quality_class=self.quality_class)
            op["heads"] = heads
        return self.opcua

    def _machine(self, d: dict[str, Any], web: dict[str, Any]) -> bool:
        if self.web and d != self._sent_machine:
            web["machine"] = self._sent_machine = dict(d)
        if self.heads is not None:
            self.heads.take_machine(d)
            return True
        return False

    def _head_item(self, kind: str, head: str, item: Any, web: dict[str, Any],
                   op: dict[str, Any], head_status: dict[str, Any]) -> bool:
        """One head's item; whether the OPC UA values changed."""
        heads = self.heads
        if heads is not None and head not in heads.configs:
            heads = None  # a head the composition did not announce: shown on the page only
        if kind == "status":
            head_status[head] = item
            if heads is not None:
                heads.update(head, item)
        elif kind == "event":
            if self.web:
                web["events"].append({**event_json(item), "head": head})
            if heads is not None:
                op["events"].append(heads.event(head, item))
        elif kind == "result":
            if self.web:
                web["results"].append({**result_json(item), "head": head})
            if heads is not None:
                heads.result(head, item)
        elif kind == "plc":
            web.setdefault("head_plc", {})[head] = item
            if heads is not None:
                heads.take_plc(head, item)
        elif kind == "counts_per_mm":
            web.setdefault("head_counts_per_mm", {})[head] = item
        elif kind == "service":
            web.setdefault("head_qc", {})[head] = item
            if heads is not None:
                heads.set_quality_class(head, item)
        return heads is not None and kind in ("status", "result", "plc", "service")
