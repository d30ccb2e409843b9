"""OPC UA's limits in the servers' process: connection cap, shortest publishing interval,
refused writes logged once per period with the count of the suppressed."""

from __future__ import annotations

import asyncio
import contextlib

import pytest

asyncua = pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
pytest.importorskip("starlette", reason="the web extra (starlette) is not installed")

from asyncua import Client, ua  # noqa: E402

from config.machine import load_machine  # noqa: E402
from controller.edge.compose import serving  # noqa: E402
from controller.edge.limits import ServerLimits  # noqa: E402
from controller.opcua.nodes import OWN_URI  # noqa: E402

WAIT_S = 60.0


async def _node(client: Client, path: str):
    own = await client.get_namespace_index(OWN_URI)
    return client.get_node(f"ns={own};s=SmartPlaner.{path.replace('/', '.')}")


def test_limits_hold_in_the_servers_process(tmp_path):
    cfg = load_machine(None)
    limits = ServerLimits(opcua_max_connections=2, opcua_min_publishing_ms=200.0,
                          log_every_s=600.0)

    async def main() -> dict:
        async with serving(cfg, lambda: None, opcua="opc.tcp://127.0.0.1:0",
                           limits=limits) as servers:
            assert servers.url is None and servers.endpoint.startswith("opc.tcp://127.0.0.1:")
            a, b, c = (Client(servers.endpoint, timeout=10) for _ in range(3))
            await a.connect()
            await b.connect()
            try:
                with pytest.raises((ConnectionError, OSError, asyncio.TimeoutError,
                                    ua.UaError)):
                    await c.connect()  # the third: over the cap
                sub = await a.create_subscription(10, None)
                revised = sub.parameters.RequestedPublishingInterval
                node = await _node(a, "State/Machine/Flags/Error")
                refused = 0
                for _ in range(40):
                    try:
                        await node.write_value(ua.DataValue(ua.Variant(True,
                                                                       ua.VariantType.Boolean)))
                    except ua.UaStatusCodeError:
                        refused += 1
                stats = await asyncio.to_thread(
                    servers.wait_stats, lambda s: s["log"]["suppressed"] >= refused - 2,
                    WAIT_S)
                return {"revised": revised, "refused": refused, "stats": stats}
            finally:
                for cl in (a, b):
                    with contextlib.suppress(Exception):
                        await cl.disconnect()

    got = asyncio.run(main())
    assert got["revised"] == 200.0  # asked for 10 ms, granted the floor
    assert got["refused"] == 40
    log = got["stats"]["log"]
    # 40 refused writes: a line or two per kind, the rest counted
    assert log["emitted"] <= 6 and log["suppressed"] >= 38, log
    assert got["stats"]["opcua"]["connections"] <= 2
