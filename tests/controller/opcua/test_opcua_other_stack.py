"""A client of another OPC UA stack (node-opcua, Node.js) sees what the asyncua client sees.

Needs ``node`` on PATH and the npm package ``node-opcua-client``, found through the environment
variable ``NODE_OPCUA_PATH`` (a ``node_modules`` folder, e.g. after ``npm install --prefix
DIR node-opcua-client@2.186.4`` use ``DIR/node_modules``) or Node's own module resolution; the
test skips with the reason otherwise.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import subprocess
import threading
import time

import pytest

pytest.importorskip("asyncua")

from asyncua import Client  # noqa: E402

from controller.opcua.nodes import DI_URI, MACHINERY_URI, WW_URI  # noqa: E402
from controller.opcua.server import OpcUaServer  # noqa: E402
from controller.service.status import ServiceStatus  # noqa: E402

BROWSE_JS = r"""
const { OPCUAClient, AttributeIds, BrowseDirection, makeBrowsePath } =
  require("node-opcua-client");
(async () => {
  const client = OPCUAClient.create({ endpointMustExist: false,
    connectionStrategy: { maxRetry: 0 } });
  await client.connect(process.argv[2]);
  const session = await client.createSession();
  const nsArray = await session.readNamespaceArray();
  const MA = nsArray.indexOf(process.argv[3]), DI = nsArray.indexOf(process.argv[4]);
  const WW = nsArray.indexOf(process.argv[5]);
  const idx = { di: DI, ma: MA, ww: WW };
  const machines = await session.translateBrowsePath(
    makeBrowsePath("ObjectsFolder", `/${MA}:Machines`));
  const kids = await session.browse({ nodeId: machines.targets[0].targetId,
    browseDirection: BrowseDirection.Forward, referenceTypeId: "HierarchicalReferences",
    includeSubtypes: true, resultMask: 63 });
  const out = { instances: [], values: {} };
  for (const r of kids.references) {
    if (r.typeDefinition.namespace === WW && r.typeDefinition.value === 2) {
      out.instances.push(r.nodeId.toString());
    }
  }
  for (const p of JSON.parse(process.argv[6])) {
    const key = p.map((x) => x[1]).join("/");
    const rel = p.map(([ns, name], i) => (i === 0 && ns === "di" ? "." : "/")
      + `${idx[ns]}:${name}`).join("");
    const res = await session.translateBrowsePath(makeBrowsePath(out.instances[0], rel));
    if (!res.targets || !res.targets.length) { out.values[key] = null; continue; }
    const dv = await session.read({ nodeId: res.targets[0].targetId,
      attributeId: AttributeIds.Value });
    let v = dv.value.value;
    if (v && v.text !== undefined) v = v.text;
    out.values[key] = v;
  }
  console.log("RESULT " + JSON.stringify(out));
  await session.close();
  await client.disconnect();
})().catch((e) => { console.error(String(e)); process.exit(1); });
"""

PATHS = [
    [["ww", "State"], ["ww", "Machine"], ["ww", "Overview"], ["ww", "CurrentState"]],
    [["ww", "State"], ["ww", "Machine"], ["ww", "Overview"], ["ww", "CurrentMode"]],
    [["ww", "State"], ["ww", "Machine"], ["ww", "Flags"], ["ww", "Error"]],
    [["ww", "State"], ["ww", "Machine"], ["ww", "Flags"], ["ww", "FeedRuns"]],
    [["ww", "State"], ["ww", "Machine"], ["ww", "Values"], ["ww", "FeedSpeed"]],
    [["di", "Identification"], ["di", "Manufacturer"]],
    [["di", "Identification"], ["di", "SerialNumber"]],
    [["di", "Identification"], ["ma", "YearOfConstruction"]],
]


def _node_env(tmp_path) -> dict[str, str]:
    if shutil.which("node") is None:
        pytest.skip("node (Node.js) not on PATH")
    env = {**os.environ, "HOME": str(tmp_path), "XDG_CONFIG_HOME": str(tmp_path / "config")}
    if os.environ.get("NODE_OPCUA_PATH"):
        env["NODE_PATH"] = os.environ["NODE_OPCUA_PATH"]
    probe = subprocess.run(["node", "-e", "require.resolve('node-opcua-client')"], env=env,
                           capture_output=True, timeout=60)
    if probe.returncode != 0:
        pytest.skip("npm package node-opcua-client not found (set NODE_OPCUA_PATH)")
    return env


def test_node_opcua_client_sees_the_same(tmp_path):
    env = _node_env(tmp_path)
    script = tmp_path / "browse.js"
    script.write_text(BROWSE_JS, encoding="utf-8")
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    srv = OpcUaServer("opc.tcp://127.0.0.1:0", knives=4,
                      identification={"Manufacturer": "ACME", "SerialNumber": "SN-7"})
    try:
        asyncio.run_coroutine_threadsafe(srv.start(), loop).result(timeout=120)
        before = srv.published
        srv.update(ServiceStatus(
            t_s=5.0, state="run", safe_reason=None, missing=(), feed_setpoint_mm_s=300.0,
            feed_actual_mm_s=300.0, offsets_um=(0.0,) * 4, amplifier_enabled=True,
            last_measurement=None, counters=ServiceStatus.freeze({})))
        deadline = time.monotonic() + 30
        while srv.published == before:
            assert time.monotonic() < deadline, "the server never published the update"
            time.sleep(0.002)
        proc = subprocess.run(
            ["node", str(script), srv.endpoint, MACHINERY_URI, DI_URI, WW_URI, json.dumps(PATHS)],
            env=env, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr[-2000:]
        lines = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
        assert len(lines) == 1, proc.stdout[-2000:]
        seen = json.loads(lines[0][len("RESULT "):])

        async def with_asyncua():
            async with Client(srv.endpoint) as c:
                idx = {"di": await c.get_namespace_index(DI_URI),
                       "ma": await c.get_namespace_index(MACHINERY_URI),
                       "ww": await c.get_namespace_index(WW_URI)}
                out = {}
                for p in PATHS:
                    node = await srv_machine(c).get_child([f"{idx[ns]}:{name}" for ns, name in p])
                    v = await node.read_value()
                    out["/".join(name for _, name in p)] = getattr(v, "Text", v)
                return out

        def srv_machine(c):
            return c.get_node(srv.nodes.machine.nodeid)

        mine = asyncio.run(with_asyncua())
    finally:
        asyncio.run_coroutine_threadsafe(srv.stop(), loop).result(timeout=60)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=60)
    assert seen["instances"] == [srv.nodes.machine.nodeid.to_string()]
    assert seen["values"] == mine
    v = seen["values"]
    assert v["State/Machine/Overview/CurrentState"] == 3  # WORKING
    assert v["State/Machine/Flags/FeedRuns"] is True
    assert v["State/Machine/Values/FeedSpeed"] == pytest.approx(300.0 * 0.06)
    assert v["Identification/Manufacturer"] == "ACME"
