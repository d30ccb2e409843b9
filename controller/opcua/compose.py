"""The OPC UA server that machine.toml asks for (``planer serve``, ``planer hil``).

Imports asyncua only when a server is asked for (``--opcua`` or ``[opcua] endpoint``), so the
commands run without the ``opcua`` extra installed. The server runs in the servers' process
(:func:`controller.edge.compose.serving`).
"""

from __future__ import annotations

from typing import Any

from config.machine import MachineConfig

__all__ = ["opcua_options", "server_for"]


def opcua_options(cfg: MachineConfig, endpoint: str | None = None) -> dict[str, Any] | None:
    """The :class:`~controller.opcua.server.OpcUaServer` arguments ``cfg`` asks for, or ``None``.

    Checked (a server is built, not started), so a bad endpoint fails before anything starts.

    Parameters
    ----------
    cfg : MachineConfig
        ``[opcua]`` (endpoint, certificate, private key, users file), ``[identification]``,
        ``[quality]``.
    endpoint : str, optional
        ``--opcua``: overrides ``[opcua] endpoint``.

    Returns
    -------
    dict or None
        ``endpoint``, ``identification``, ``quality_class``, ``security`` (picklable).

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
    options = {
        "endpoint": endpoint,
        "identification": dict(cfg.identification),
        "quality_class": quality_class_of(cfg),
        "security": OpcUaSecurity(certificate=op.certificate, private_key=op.private_key,
                                  users_file=op.users_file),
    }
    OpcUaServer(**options)  # checks the endpoint, the security files, the users
    return options


def server_for(cfg: MachineConfig, endpoint: str | None = None) -> Any:
    """The :class:`~controller.opcua.server.OpcUaServer` that ``cfg`` asks for, or ``None``.

    Raises
    ------
    ValueError
        As :func:`opcua_options`.
    """
    options = opcua_options(cfg, endpoint)
    if options is None:
        return None
    from controller.opcua.server import OpcUaServer

    return OpcUaServer(**options)
