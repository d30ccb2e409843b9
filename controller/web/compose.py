"""The web pages that machine.toml asks for (``planer serve``, ``planer hil``).

Imports Starlette and uvicorn only when a server is asked for (``--http`` or ``[http]
listen``), so the commands run without the ``web`` extra installed. The pages run in the
servers' process (:func:`controller.edge.compose.serving`).
"""

from __future__ import annotations

from config.machine import MachineConfig

__all__ = ["listen_for"]


def listen_for(cfg: MachineConfig, listen: str | None = None) -> str | None:
    """The ``HOST:PORT`` asked for (``--http`` over ``[http] listen``), ``None`` when off.

    Checked, so a bad address fails before anything starts.

    Raises
    ------
    ValueError
        A bad address, or Starlette / uvicorn missing.
    """
    from controller.web.server import parse_listen

    http = getattr(cfg, "http", None)
    listen = listen or (getattr(http, "listen", "") if http is not None else "")
    if not listen:
        return None
    parse_listen(listen)
    try:
        import starlette  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as exc:
        raise ValueError(f"http {listen}: the web pages need starlette and uvicorn "
                         f"(pip install 'smart-planer[web]'): {exc}") from None
    return listen
