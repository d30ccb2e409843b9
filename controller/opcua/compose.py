"""The OPC UA server in a composition (``planer serve``, ``planer hil``): from machine.toml.

Imports asyncua only when a server is asked for (``--opcua`` or ``[opcua] endpoint``), so the
commands run without the ``opcua`` extra installed.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

from config.machine import MachineConfig

__all__ = ["serving", "server_for"]


def server_for(cfg: MachineConfig, endpoint: str | None = None) -> Any:
    """The :class:`~controller.opcua.server.OpcUaServer` that ``cfg`` asks for, or ``None``.

    Parameters
    ----------
    cfg : MachineConfig
        ``[opcua]`` (endpoint, certificate, private key, users file), ``[identification]``,
        ``[quality]``.
    endpoint : str, optional
        ``--opcua``: overrides ``[opcua] endpoint``.

    Raises
    ------
    ValueError
        A bad endpoint, a non-loopback address without certificate and users, asyncua missing.
    """
    endpoint = endpoint or cfg.opcua.endpoint
    if not endpoint:
        return None
    try:
        from controller.opcua.server import OpcUaSecurity, OpcUaServer
    except ImportError as exc:
        raise ValueError(f"opcua endpoint {endpoint}: the OPC UA server needs asyncua "
                         f"(pip install 'smart-planer[opcua]'): {exc}") from None
    from controller.service.records import quality_class_of

    op = cfg.opcua
    return OpcUaServer(
        endpoint,
        identification=dict(cfg.identification),
        quality_class=quality_class_of(cfg),
        security=OpcUaSecurity(certificate=op.certificate, private_key=op.private_key,
                               users_file=op.users_file),
    )


@asynccontextmanager
async def serving(
    cfg: MachineConfig,
    endpoint: str | None,
    get_service: Callable[[], Any],
    *,
    say: Callable[[str], None] | None = None,
    period_s: float = 0.2,
) -> AsyncIterator[Any]:
    """Serve OPC UA (when asked for) while the block runs, following ``get_service()``.

    Yields the started server, or ``None`` when OPC UA is off. A busy port raises ``OSError``
    (one line naming it) before the block starts.
    """
    server = server_for(cfg, endpoint)
    if server is None:
        yield None
        return
    await server.start()
    if say is not None:
        say(f"opcua: {server.endpoint} (WwMachineType under Objects/Machines)")
    task = asyncio.create_task(server.follow(get_service, period_s=period_s))
    try:
        yield server
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        await server.stop()
