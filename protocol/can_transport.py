"""Opening a python-can bus from configuration, and a private network namespace for CAN over UDP.

Transports (the ``[can]`` table: ``interface``, ``channel``, extra options):

=============  ==========================  =====================================================
interface      channel                     use
=============  ==========================  =====================================================
virtual        any name                    in-process tests (python-can's virtual bus)
udp_multicast  IPv4 group, "239.74.163.2"  between processes on one host, inside a private
                                           network namespace (``run_in_private_netns``); needs
                                           ``msgpack`` (python-can's ``multicast`` extra)
remote         "ws://127.0.0.1:54701/"     python-can-remote server on loopback (not installed)
socketcan      "can0"                      the machine
=============  ==========================  =====================================================

UDP multicast leaves the host when the network has other interfaces than ``lo``; so
``open_bus`` refuses ``udp_multicast`` unless the process sees no interface but ``lo`` (a
private namespace made by ``unshare -rn``), or the option ``loopback_only = false`` is given.
Every python-can bus on udp_multicast also receives the frames it sent itself: receivers must
ignore the ids they send.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from collections.abc import Mapping, Sequence
from functools import lru_cache
from typing import Any

from core.errors import ConfigError, FieldbusError

INTERFACES = ("virtual", "udp_multicast", "remote", "socketcan")
DEFAULT_MULTICAST_GROUP = "239.74.163.2"
NETNS_ENV = "PLANER_PRIVATE_NETNS"
"""Environment variable set to ``1`` inside a namespace made by :func:`netns_argv`."""

_NETNS_SETUP = "ip link set lo up && ip route add 224.0.0.0/4 dev lo"


def network_interfaces() -> list[str]:
    """Names of this process's network interfaces (``["lo"]`` inside a private namespace)."""
    try:
        return [name for _i, name in socket.if_nameindex()]
    except OSError:  # pragma: no cover - exotic platforms
        return []


def only_loopback() -> bool:
    """Whether this process can reach no network but loopback (a private network namespace)."""
    names = network_interfaces()
    return bool(names) and all(n == "lo" for n in names)


def multicast_refused_message(interfaces: Sequence[str]) -> str:
    """Why ``udp_multicast`` was refused and what to do, in words (one line).

    Parameters
    ----------
    interfaces : sequence of str
        The network interfaces this process sees.
    """
    seen = ", ".join(interfaces) or "unknown"
    return (
        f"udp_multicast would reach the network outside this host (this process sees the "
        f"network interfaces {seen}): start the simulator and the service inside one private "
        "network namespace, the simulator with unshare and the service joining it with "
        "nsenter, as README.md shows under \"Simulator and service in two terminals\" "
        "(details in docs/service.md), or let planer hil do all of that by itself"
    )


def open_bus(interface: str, channel: str | None = None, **options: Any) -> Any:
    """Open a python-can bus.

    Parameters
    ----------
    interface : str
        ``virtual``, ``udp_multicast``, ``remote`` or ``socketcan`` (other python-can interfaces
        are passed through).
    channel : str, optional
        Bus name, multicast group, server URL or device; defaults: ``"planer"`` (virtual),
        ``239.74.163.2`` (udp_multicast), ``can0`` (socketcan).
    **options
        Passed to ``can.Bus`` (``port``, ``bitrate``, ``receive_own_messages``...), except
        ``loopback_only`` (udp_multicast: refuse unless only ``lo`` exists; default true).

    Returns
    -------
    can.BusABC

    Raises
    ------
    FieldbusError
        The bus cannot be opened (missing package, no such device, multicast off loopback).
    """
    import can

    opts = dict(options)
    loopback_only = bool(opts.pop("loopback_only", True))
    if interface == "virtual":
        channel = channel or "planer"
        opts.setdefault("receive_own_messages", False)
    elif interface == "udp_multicast":
        channel = channel or DEFAULT_MULTICAST_GROUP
        opts.setdefault("fd", False)
        if loopback_only and not only_loopback():
            raise FieldbusError(multicast_refused_message(network_interfaces()))
        try:
            import msgpack  # noqa: F401
        except ImportError:
            raise FieldbusError(
                "CAN interface udp_multicast needs the msgpack package "
                "(pip install 'python-can[multicast]')"
            ) from None
    elif interface == "remote":
        channel = channel or "ws://127.0.0.1:54701/"
    elif interface == "socketcan":
        channel = channel or "can0"
    try:
        return can.Bus(interface=interface, channel=channel, **opts)
    except ImportError as exc:
        raise FieldbusError(f"CAN interface {interface} is not installed: {exc}") from None
    except (can.CanError, OSError, ValueError, RuntimeError, NotImplementedError) as exc:
        raise FieldbusError(f"cannot open CAN bus {interface}:{channel}: {exc}") from None


def bus_from_config(can_cfg: Any) -> Any:
    """Open the bus a ``[can]`` configuration table describes.

    Parameters
    ----------
    can_cfg : object or mapping
        Has ``interface``, ``channel`` and ``options`` (a mapping of extra keyword options),
        as attributes (``SimConfig.can``) or keys.
    """
    if isinstance(can_cfg, Mapping):
        get = can_cfg.get
    else:

        def get(key: str, default: Any = None) -> Any:
            return getattr(can_cfg, key, default)

    interface = get("interface")
    if interface is None:
        raise ConfigError("missing key can.interface")
    options = dict(get("options", None) or {})
    return open_bus(str(interface), get("channel", None), **options)


# ---------------------------------------------------------------------- private network namespace
@lru_cache(maxsize=1)
def _unshare_flag() -> str:
    """``unshare``'s flag: ``-n`` for root with the right to, else ``-rn``.

    Inside a user namespace (``-r``) a process loses the right to real-time scheduling that the
    simulated PLC and the service's bus thread ask for (:mod:`core.realtime`).
    """
    if hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("unshare"):
        try:
            res = subprocess.run(["unshare", "-n", "true"], capture_output=True, timeout=10,
                                 check=False)
        except (OSError, subprocess.SubprocessError):
            return "-rn"
        if res.returncode == 0:
            return "-n"
    return "-rn"


def netns_argv(argv: Sequence[str]) -> list[str]:
    """Command line running ``argv`` in a new private network namespace with lo and multicast.

    ``unshare -rn`` (an unprivileged user and network namespace; ``unshare -n`` when run as
    root with the right to, so real-time scheduling stays permitted inside), ``ip link set lo
    up``, ``ip route add 224.0.0.0/4 dev lo``, then ``exec argv`` with
    ``PLANER_PRIVATE_NETNS=1``. Every process ``argv`` starts shares that namespace (and can
    reach only loopback).
    """
    if not argv:
        raise ValueError("argv must not be empty")
    script = f'{_NETNS_SETUP} && export {NETNS_ENV}=1 && exec "$@"'
    return ["unshare", _unshare_flag(), "sh", "-c", script, "planer-netns", *map(str, argv)]


@lru_cache(maxsize=1)
def private_netns_available() -> bool:
    """Whether ``unshare -rn`` and ``ip`` work here (checked once per process)."""
    if not shutil.which("unshare") or not shutil.which("ip"):
        return False
    try:
        res = subprocess.run(netns_argv(["true"]), capture_output=True, timeout=10, check=False)
    except (OSError, subprocess.SubprocessError):
        return False
    return res.returncode == 0


def in_private_netns() -> bool:
    """Whether this process runs in a namespace made by :func:`netns_argv`."""
    return os.environ.get(NETNS_ENV) == "1" and only_loopback()


def run_in_private_netns(argv: Sequence[str], **popen_kwargs: Any) -> subprocess.Popen:
    """Start ``argv`` in a new private network namespace; returns the ``Popen``.

    Start the whole group that must talk over ``udp_multicast`` (simulator and service) from
    one process inside the namespace, e.g. ``run_in_private_netns(["planer", "hil", ...])``
    whose children then share it; or use :func:`reexec_in_private_netns` at the top of a
    command.

    Raises
    ------
    FieldbusError
        ``unshare -rn`` is not permitted here (no unprivileged user namespaces).
    """
    if not private_netns_available():
        raise FieldbusError(
            "cannot create a private network namespace (unshare -rn / ip not permitted here)"
        )
    return subprocess.Popen(netns_argv(argv), **popen_kwargs)


def reexec_in_private_netns(argv: Sequence[str] | None = None) -> None:
    """Replace this process by itself running inside a private network namespace.

    Does nothing when already inside one (``PLANER_PRIVATE_NETNS=1``). ``argv`` defaults to
    ``[sys.executable, *sys.argv]``. Never returns otherwise.

    Raises
    ------
    FieldbusError
        ``unshare -rn`` is not permitted here.
    """
    if in_private_netns():
        return
    if not private_netns_available():
        raise FieldbusError(
            "cannot create a private network namespace (unshare -rn / ip not permitted here)"
        )
    args = list(argv) if argv is not None else [sys.executable, *sys.argv]
    sys.stdout.flush()
    sys.stderr.flush()
    cmd = netns_argv(args)
    os.execvp(cmd[0], cmd)


def describe_bus(interface: str, channel: str | None) -> str:
    """One line naming the bus, for banners."""
    return f"{interface}:{channel}" if channel else interface


__all__ = [
    "DEFAULT_MULTICAST_GROUP",
    "INTERFACES",
    "NETNS_ENV",
    "bus_from_config",
    "describe_bus",
    "in_private_netns",
    "multicast_refused_message",
    "netns_argv",
    "network_interfaces",
    "only_loopback",
    "open_bus",
    "private_netns_available",
    "reexec_in_private_netns",
    "run_in_private_netns",
]
