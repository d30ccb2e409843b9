"""The machine's OPC UA server at the edge: one owner, read-only for clients, fed by the service.

The service (or a test) calls :meth:`OpcUaServer.update` / :meth:`OpcUaServer.event` /
:meth:`OpcUaServer.result`. The address space is built once
(:func:`controller.opcua.nodes.build_address_space`); the values are computed by
:class:`controller.opcua.view.MachineView` (pure); this module only writes the changed values
with a source timestamp and fires the Woodworking events.

Security: on a loopback address (the default ``opc.tcp://127.0.0.1:4840``) anonymous clients may
read, without encryption. Any other address needs a server certificate and private key
(``Basic256Sha256``, ``SignAndEncrypt`` only) and a users file (user name and password); the
server refuses to start otherwise. No client may write, call or change the address space.
"""

from __future__ import annotations

import asyncio
import errno
import hashlib
import hmac
import ipaddress
import logging
import socket
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from asyncua import Server, ua
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole

from controller.opcua.heads_nodes import build_heads
from controller.opcua.nodes import MachineNodes, build_address_space
from controller.opcua.view import MachineView, WwEvent
from controller.quality.log import QualityClass
from controller.service.events import ServiceEvent
from controller.service.frame_result import FrameResult
from controller.service.status import ServiceStatus

__all__ = [
    "DEFAULT_ENDPOINT",
    "OpcUaSecurity",
    "OpcUaServer",
    "endpoint_security",
    "hash_password",
    "load_users",
    "parse_endpoint",
]

DEFAULT_ENDPOINT = "opc.tcp://127.0.0.1:4840"
_log = logging.getLogger(__name__)
_DISPLAY_ERRORS = (ua.UaError, OSError, ValueError, TypeError, AttributeError, KeyError,
                   IndexError, RuntimeError)
"""What a publishing or following round may fail with; logged, never raised into the service."""

_READ_ONLY_IDS = {
    ua.NodeId(i) for i in USER_TYPES
    if i not in (ua.ObjectIds.WriteRequest_Encoding_DefaultBinary,
                 ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
}


class _ReadOnly(PermissionRuleset):
    """Every role may browse, read and subscribe; nobody may write, call or add nodes."""

    def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
        return action_type_id in _READ_ONLY_IDS


def hash_password(password: str, *, salt: bytes | None = None, iterations: int = 200_000) -> str:
    """A users-file entry's secret: ``pbkdf2_sha256$ITERATIONS$SALT_HEX$HASH_HEX``."""
    import os

    salt = os.urandom(16) if salt is None else salt
    digest = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    return f"pbkdf2_sha256${iterations}${salt.hex()}${digest.hex()}"


def _check_password(password: str, secret: str) -> bool:
    try:
        algo, iterations, salt_hex, hash_hex = secret.split("$")
        if algo != "pbkdf2_sha256":
            return False
        digest = hashlib.pbkdf2_hmac("sha256", password.encode(), bytes.fromhex(salt_hex),
                                     int(iterations))
    except ValueError:
        return False
    return hmac.compare_digest(digest.hex(), hash_hex)


def load_users(path: Path) -> dict[str, str]:
    """Read a users file: one ``name:pbkdf2_sha256$...`` line per user (``#`` comments)."""
    users: dict[str, str] = {}
    for n, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        name, sep, secret = line.partition(":")
        if not sep or not name or not secret.startswith("pbkdf2_sha256$"):
            raise ValueError(f"{path}:{n}: expected name:pbkdf2_sha256$..., "
                             "made with controller.opcua.server.hash_password")
        users[name] = secret
    if not users:
        raise ValueError(f"{path}: no users")
    return users


class _Users:
    """asyncua user manager: anonymous (when offered) and users-file names, never admin."""

    def __init__(self, users: Mapping[str, str]) -> None:
        self._users = dict(users)

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if username is None:  # anonymous: that token is only offered on loopback
            return User(role=UserRole.User)
        secret = self._users.get(username)
        if secret is None or not _check_password(password or "", secret):
            return None
        return User(role=UserRole.User, name=username)


@dataclass(frozen=True)
class OpcUaSecurity:
    """How clients authenticate and how the channel is protected.

    Attributes
    ----------
    certificate, private_key : Path or None
        The server's certificate (DER or PEM) and private key (PEM). With both, the endpoints
        ``Basic256Sha256`` ``SignAndEncrypt`` are offered.
    users_file : Path or None
        User names and password hashes (:func:`load_users`); required off loopback, where it
        replaces anonymous access.
    """

    certificate: Path | None = None
    private_key: Path | None = None
    users_file: Path | None = None


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def endpoint_security(
    host: str, *, has_certificate: bool, has_users: bool
) -> tuple[tuple[ua.SecurityPolicyType, ...], tuple[type, ...]]:
    """The security policies and user token types offered on ``host``.

    Loopback: ``None`` with anonymous (plus ``Basic256Sha256 SignAndEncrypt`` with a
    certificate, user names with a users file). Elsewhere: only ``Basic256Sha256
    SignAndEncrypt`` with user names; ``ValueError`` without a certificate or users.
    """
    loopback = _is_loopback(host)
    if not loopback and not (has_certificate and has_users):
        raise ValueError(
            f"opcua endpoint on {host}: binding to a non-loopback address needs a server "
            "certificate and private key (Basic256Sha256 SignAndEncrypt) and a users file; "
            "see docs/opcua.md"
        )
    policies = [ua.SecurityPolicyType.NoSecurity] if loopback else []
    if has_certificate:
        policies.append(ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt)
    tokens: list[type] = [ua.AnonymousIdentityToken] if loopback else []
    if has_users:
        tokens.append(ua.UserNameIdentityToken)
    return tuple(policies), tuple(tokens)


def parse_endpoint(endpoint: str) -> tuple[str, int]:
    """``opc.tcp://HOST:PORT`` -> ``(host, port)``; ``ValueError`` naming the endpoint."""
    if not isinstance(endpoint, str):
        raise ValueError(f"opcua endpoint must be a string, got {type(endpoint).__name__}")
    u = urlparse(endpoint)
    try:
        port = u.port
    except ValueError:
        port = None
    if u.scheme != "opc.tcp" or not u.hostname or port is None:
        raise ValueError(
            f"opcua endpoint must look like opc.tcp://127.0.0.1:4840, got {endpoint!r}")
    return u.hostname, port


class OpcUaServer:
    """The machine's OPC UA server (OPC 40550 Woodworking), fed by the service.

    Parameters
    ----------
    endpoint : str
        ``opc.tcp://HOST:PORT`` (port 0: an ephemeral port, see :attr:`endpoint` after start).
    identification : mapping
        ``Identification`` values (``Manufacturer``, ``Model``, ``SerialNumber``,
        ``YearOfConstruction``, ...; :data:`controller.opcua.nodes.IDENTIFICATION_FIELDS`).
    quality_class : QualityClass or None
        The class each measurement is judged against (``ManufacturerSpecific/Passed``).
    calibrated : bool
        ``Flags/Calibrated``.
    knives : int
        Knife count (initial length of the per-knife arrays).
    security : OpcUaSecurity
        Certificates and users; required for a non-loopback host.
    wall_clock : callable
        Returns the UTC ``datetime`` used as source timestamp (injected in tests).
    max_connections : int, keyword-only
        TCP connections at once; asyncua closes one more on accept.
    max_subscriptions : int, keyword-only
        Subscriptions on the whole server (``BadTooManySubscriptions`` past it).
    min_publishing_ms : float, keyword-only
        Shortest publishing interval granted, ms (a client asking for less gets this).
    activation_s : float, keyword-only
        A connection that has not activated a session this long after connecting is closed, s.
    max_session_timeout_ms : float, keyword-only
        Longest session timeout granted, ms.
    heads : sequence of mapping, keyword-only, optional
        A moulder's heads (``name``, ``knives``, ...: :func:`controller.edge.feed.
        head_configs_json`), built at start as ``State/SubUnits/<head>``; ``None``: one head,
        the address space of a single machine (heads told later by :meth:`apply` are added
        then).
    """

    def __init__(
        self,
        endpoint: str = DEFAULT_ENDPOINT,
        *,
        identification: Mapping[str, Any] | None = None,
        quality_class: QualityClass | None = None,
        calibrated: bool = True,
        knives: int = 0,
        security: OpcUaSecurity | None = None,
        wall_clock: Callable[[], datetime] | None = None,
        max_connections: int = 32,
        max_subscriptions: int = 64,
        min_publishing_ms: float = 100.0,
        activation_s: float = 10.0,
        max_session_timeout_ms: float = 60_000.0,
        heads: Sequence[Mapping[str, Any]] | None = None,
    ) -> None:
        self.host, self.port = parse_endpoint(endpoint)
        self.limits = _check_limits(max_connections=max_connections,
                                    max_subscriptions=max_subscriptions,
                                    min_publishing_ms=min_publishing_ms,
                                    activation_s=activation_s,
                                    max_session_timeout_ms=max_session_timeout_ms)
        self.security = security or OpcUaSecurity()
        sec = self.security
        if (sec.certificate is None) != (sec.private_key is None):
            raise ValueError("opcua: certificate and private_key go together")
        if not _is_loopback(self.host) and (sec.certificate is None or sec.users_file is None):
            raise ValueError(
                f"opcua endpoint {endpoint}: binding to a non-loopback address needs a server "
                "certificate and private key (Basic256Sha256 SignAndEncrypt) and a users file; "
                "see docs/opcua.md"
            )
        for name in ("certificate", "private_key", "users_file"):
            path = getattr(sec, name)
            if path is not None and not Path(path).is_file():
                raise ValueError(f"opcua {name}: no such file: {path}")
        self._users = load_users(sec.users_file) if sec.users_file is not None else {}
        self.identification = dict(identification or {})
        self.knives = int(knives)
        self.view = MachineView(quality_class=quality_class, calibrated=calibrated)
        self._wall = wall_clock or (lambda: datetime.now(timezone.utc))
        self._lock = threading.Lock()
        self._pending_events: list[WwEvent] = []
        self._dirty = False
        self._values: dict[str, Any] | None = None  # given by apply(), instead of the view's
        self._written: dict[str, Any] = {}
        self._server: Server | None = None
        self._nodes: MachineNodes | None = None
        self._wake: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._gen: Any = None
        self._new_heads: list[dict[str, Any]] = [dict(h) for h in heads or ()]
        self.published = 0
        """Publish rounds done (tests poll it)."""

    # --- lifecycle ----------------------------------------------------------------------------

    @property
    def endpoint(self) -> str:
        """The endpoint clients connect to (the real port after an ephemeral bind)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"opc.tcp://{host}:{self.port}"

    @property
    def nodes(self) -> MachineNodes:
        """The address space's writable parts (after :meth:`start`)."""
        if self._nodes is None:
            raise RuntimeError("OpcUaServer not started")
        return self._nodes

    async def start(self) -> None:
        """Build the address space and listen; a busy port raises ``OSError`` in one line."""
        self._check_port()
        server = Server(user_manager=_Users(self._users))
        await server.init()
        server.set_endpoint(self.endpoint + "/")
        server.set_server_name("smart-planer")
        await server.set_application_uri("urn:smart-planer:server")
        sec = self.security
        if sec.certificate is not None and sec.private_key is not None:
            await server.load_certificate(str(sec.certificate))
            await server.load_private_key(str(sec.private_key))
        policies, tokens = endpoint_security(
            self.host, has_certificate=sec.certificate is not None, has_users=bool(self._users))
        server.set_security_policy(list(policies), permission_ruleset=_ReadOnly())
        server.set_identity_tokens(list(tokens))
        _apply_limits(server, self.limits)
        self._nodes = await build_address_space(server, self.identification, knives=self.knives)
        await self._build_heads(server)
        self._gen = await server.get_event_generator(self._nodes.event_type,
                                                     self._nodes.events_node)
        try:
            await server.start()
        except OSError as exc:
            await _quiet_stop(server)
            raise self._listen_error(exc) from None
        if self.port == 0:
            sockets = server.bserver._server.sockets if server.bserver and server.bserver._server \
                else []
            if sockets:
                self.port = sockets[0].getsockname()[1]
        self._server = server
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        await self._publish()
        self._task = asyncio.create_task(self._run(), name="opcua-publish")

    def _listen_error(self, exc: OSError) -> OSError:
        if exc.errno == errno.EADDRINUSE:
            msg = (f"opcua endpoint {self.endpoint}: port {self.port} is busy "
                   "(another server listens there)")
        else:
            msg = f"opcua endpoint {self.endpoint}: cannot listen: {exc.strerror or exc}"
        err = OSError(msg)
        err.errno = exc.errno
        return err

    def _check_port(self) -> None:
        """Fail fast (before the address space is built) when the port is taken."""
        if self.port == 0:
            return
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((self.host, self.port))
            except OSError as exc:
                raise self._listen_error(exc) from None

    def clients(self) -> dict[str, int]:
        """``connections`` and ``subscriptions`` held now, ``published`` rounds (0 unstarted)."""
        server = self._server
        if server is None:
            return {"connections": 0, "subscriptions": 0, "published": self.published}
        bserver = server.bserver
        return {"connections": len(bserver.clients) if bserver is not None else 0,
                "subscriptions": len(server.iserver.subscription_service.subscriptions),
                "published": self.published}

    async def stop(self) -> None:
        """Stop serving (idempotent)."""
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
            self._task = None
        if self._server is not None:
            server, self._server = self._server, None
            await _quiet_stop(server)

    async def __aenter__(self) -> OpcUaServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # --- the service's side (thread-safe, never blocks) ----------------------------------------

    def update(self, status: ServiceStatus) -> None:
        """A new status snapshot (``service.status()``)."""
        with self._lock:
            self.view.update(status)
            self._dirty = True
        self._poke()

    def event(self, e: ServiceEvent) -> None:
        """A service event (``service.on_event``): fired as a ``WwBaseEventType`` event."""
        with self._lock:
            self._pending_events.append(self.view.event(e))
        self._poke()

    def result(self, r: FrameResult) -> None:
        """A pair's result (``service.on_result``)."""
        with self._lock:
            self.view.result(r)
            self._dirty = True
        self._poke()

    def apply(self, values: Mapping[str, Any] | None, events: list[WwEvent],
              heads: Sequence[Mapping[str, Any]] | None = None) -> None:
        """Values and events computed elsewhere (a :class:`MachineView` in another process).

        ``values`` (by path, :meth:`MachineView.all_values` or
        :meth:`~controller.opcua.heads_view.MoulderView.all_values`; ``None``: unchanged)
        replace the server's own view from now on; ``events`` are fired in order; ``heads``
        (a moulder's) are added to the address space first. Thread-safe, never blocks.
        """
        with self._lock:
            if heads:
                self._new_heads.extend(dict(h) for h in heads)
                self._dirty = True
            if values is not None:
                self._values = dict(values)
                self._dirty = True
            self._pending_events.extend(events)
        self._poke()

    def attach(self, service: Any, *, period_s: float = 0.2) -> asyncio.Task[None]:
        """Follow a service: chain its ``on_event``/``on_result``, poll ``status()``.

        Returns the polling task (cancelled by :meth:`stop`'s caller or at loop end).
        """
        if not period_s > 0:
            raise ValueError(f"period_s must be > 0, got {period_s}")
        prev_event, prev_result = service.on_event, service.on_result

        def on_event(e: ServiceEvent) -> None:
            self.event(e)
            if prev_event is not None:
                prev_event(e)

        def on_result(r: FrameResult) -> None:
            self.result(r)
            if prev_result is not None:
                prev_result(r)

        service.on_event, service.on_result = on_event, on_result

        async def poll() -> None:
            while True:
                self.update(service.status())
                await asyncio.sleep(period_s)

        return asyncio.create_task(poll(), name="opcua-status")

    async def follow(self, get_service: Callable[[], Any], *, period_s: float = 0.2) -> None:
        """Follow whatever service ``get_service()`` returns (``None`` until there is one).

        Polls, every ``period_s`` seconds, the service's ``status()``, the new entries of its
        ``events`` list and (when it keeps them) of its ``results`` list -- no callbacks taken,
        so compositions that set ``on_event`` / ``on_result`` themselves keep them. Runs until
        cancelled; a new service object (a restart) is followed from its first event.
        """
        if not period_s > 0:
            raise ValueError(f"period_s must be > 0, got {period_s}")
        current, n_events, n_results = None, 0, 0
        while True:
            service = get_service()
            if service is not None:
                if service is not current:
                    current, n_events, n_results = service, 0, 0
                try:
                    new_events = getattr(service, "events", [])[n_events:]
                    for e in new_events:
                        self.event(e)
                    n_events += len(new_events)
                    new_results = (getattr(service, "results", None) or [])[n_results:]
                    for r in new_results:
                        self.result(r)
                    n_results += len(new_results)
                    self.update(service.status())
                except _DISPLAY_ERRORS:  # a display never stops the service; retry next period
                    _log.exception("opcua: following the service failed")
            await asyncio.sleep(period_s)

    # --- internals ----------------------------------------------------------------------------

    def _poke(self) -> None:
        loop, wake = self._loop, self._wake
        if loop is None or wake is None or loop.is_closed():
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            wake.set()
        else:
            loop.call_soon_threadsafe(wake.set)

    async def _run(self) -> None:
        assert self._wake is not None
        while True:
            await self._wake.wait()
            self._wake.clear()
            try:
                await self._publish()
            except _DISPLAY_ERRORS:  # never let a display problem stop the service
                _log.exception("opcua: publishing failed")

    async def _build_heads(self, server: Server) -> None:
        with self._lock:
            heads, self._new_heads = self._new_heads, []
        if heads and self._nodes is not None:
            await build_heads(server, self._nodes, heads)

    async def _publish(self) -> None:
        server, nodes = self._server, self._nodes
        if nodes is None:
            return
        if self._new_heads and server is not None:
            await self._build_heads(server)
        with self._lock:
            if self._dirty or not self._written:
                values = self._values if self._values is not None else self.view.all_values()
            else:
                values = {}
            self._dirty = False
            events, self._pending_events = self._pending_events, []
        ts = self._wall()
        srv = server if server is not None else None
        for path, value in values.items():
            if path in self._written and _same(self._written[path], value):
                continue
            node = nodes.variables[path]
            vtype = nodes.variant_types[path]
            variant = ua.Variant(list(value), vtype, is_array=True) if isinstance(value, list) \
                else ua.Variant(value, vtype)
            dv = ua.DataValue(variant, SourceTimestamp=ts, ServerTimestamp=ts)
            if srv is not None:
                await srv.write_attribute_value(node.nodeid, dv)
            else:
                await node.write_value(dv)
            self._written[path] = value
        for ev in events:
            self._fire(ev, ts)
            if srv is not None:
                await self._gen.trigger(time_attr=ts)
        self.published += 1

    def _fire(self, ev: WwEvent, ts: datetime) -> None:
        e = self._gen.event
        e.Message = ua.LocalizedText(ev.message, "en")
        e.Severity = ev.severity
        e.SourceName = "Machine"
        e.MessageId = ev.message_id
        e.PathParts = list(ev.path_parts)
        e.EventCategory = int(ev.category)
        e.Time = ts


def _check_limits(**limits: float) -> dict[str, float]:
    for name, v in limits.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0 \
                or v == float("inf"):
            raise ValueError(f"opcua {name} must be a number > 0, got {v!r}")
    for name in ("max_connections", "max_subscriptions"):
        if not isinstance(limits[name], int):
            raise ValueError(f"opcua {name} must be an integer, got {limits[name]!r}")
    return dict(limits)


def _apply_limits(server: Server, limits: Mapping[str, float]) -> None:
    """Set asyncua's own limits, and the shortest publishing interval granted."""
    iserver = server.iserver
    iserver.max_connections = int(limits["max_connections"])
    iserver.max_subscriptions = int(limits["max_subscriptions"])
    iserver.max_pending_activation_seconds = float(limits["activation_s"])
    iserver.max_session_timeout_ms = float(limits["max_session_timeout_ms"])
    iserver.min_session_timeout_ms = min(iserver.min_session_timeout_ms,
                                         float(limits["max_session_timeout_ms"]))
    service = iserver.subscription_service
    create = service.create_subscription
    floor_ms = float(limits["min_publishing_ms"])

    async def create_subscription(params: Any, callback: Any, session_id: Any,
                                  request_callback: Any = None) -> Any:
        if not params.RequestedPublishingInterval >= floor_ms:  # NaN and 0 included
            params.RequestedPublishingInterval = floor_ms
        return await create(params, callback, session_id, request_callback=request_callback)

    service.create_subscription = create_subscription


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and a != a and b != b:
        return True
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


async def _quiet_stop(server: Server) -> None:
    try:
        await server.stop()
    except _DISPLAY_ERRORS:  # a server that never listened has little to stop
        _log.debug("opcua: stop after failed start", exc_info=True)
