"""Conformance of our address space with the official nodesets.

Reads the NodeSet2 files in ../shared/data/opcua (skips when absent; never copied into the
project) and checks, through an asyncua client:

- every node our server has in the DI / Machinery / Woodworking namespaces exists there with the
  same NodeClass, BrowseName, DataType, ValueRank and enumeration fields, and each of its
  references to a standard node is in the nodeset;
- every node of the machine instance whose BrowseName lies in those namespaces matches its
  instance declaration (found by BrowseName from ``WwMachineType``): NodeClass, BrowseName,
  TypeDefinition, DataType, the reference from its parent, its interfaces; and the mandatory
  children of each declaration we instantiate are there.
"""

from __future__ import annotations

import asyncio
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import pytest

pytest.importorskip("asyncua")

from asyncua import Client, ua  # noqa: E402

from controller.opcua.nodes import DI_URI, MACHINERY_URI, OWN_URI, WW_URI  # noqa: E402
from controller.opcua.server import OpcUaServer  # noqa: E402
from controller.opcua.view import FLAG_NAMES, VALUE_NAMES  # noqa: E402

DATA = Path(__file__).resolve().parents[4] / "shared" / "data" / "opcua"
FILES = ("Opc.Ua.Di.NodeSet2.xml", "Opc.Ua.IA.NodeSet2.xml", "Opc.Ua.Machinery.NodeSet2.xml",
         "opc.ua.isa95-jobcontrol.nodeset2.xml", "Opc.Ua.Machinery.Jobs.Nodeset2.xml",
         "Opc.Ua.Woodworking.NodeSet2.xml")
UA_URI = "http://opcfoundation.org/UA/"
X = "{http://opcfoundation.org/UA/2011/03/UANodeSet.xsd}"
COMPANION = (DI_URI, MACHINERY_URI, WW_URI)
HIERARCHICAL = {"i=47", "i=46", "i=17604", "i=35"}  # HasComponent, HasProperty, HasAddIn, Organizes
HAS_TYPE_DEFINITION, HAS_SUBTYPE = "i=40", "i=45"
HAS_INTERFACE, HAS_MODELLING_RULE = "i=17603", "i=37"
MANDATORY = (UA_URI, "i=78")

pytestmark = pytest.mark.skipif(not all((DATA / f).is_file() for f in FILES),
                                reason=f"official nodesets not found in {DATA}")

Key = tuple[str, str]  # (namespace URI, "i=2")


@dataclass
class XNode:
    node_class: str
    browse_name: tuple[str, str]
    data_type: Key | None
    value_rank: int
    fields: list[tuple[str, int]] = field(default_factory=list)


@dataclass
class Reference:
    nodes: dict[Key, XNode] = field(default_factory=dict)
    refs: dict[Key, set[tuple[Key, bool, Key]]] = field(default_factory=dict)

    def add_ref(self, src: Key, rtype: Key, forward: bool, dst: Key) -> None:
        self.refs.setdefault(src, set()).add((rtype, forward, dst))
        self.refs.setdefault(dst, set()).add((rtype, not forward, src))

    def targets(self, src: Key, rtype: str, *, forward: bool = True) -> list[Key]:
        return [d for t, f, d in self.refs.get(src, ()) if t == (UA_URI, rtype) and f == forward]

    def children(self, src: Key) -> list[tuple[str, Key]]:
        return [(t[1], d) for t, f, d in self.refs.get(src, ())
                if f and t[0] == UA_URI and t[1] in HIERARCHICAL]

    def find(self, decl: Key, name: tuple[str, str], seen: set[Key] | None = None):
        """The child ``name`` of ``decl``: its own, else from its type, supertypes, interfaces."""
        seen = set() if seen is None else seen
        if decl in seen:
            return None
        seen.add(decl)
        for rtype, child in self.children(decl):
            if child in self.nodes and self.nodes[child].browse_name == name:
                return rtype, child
        node = self.nodes.get(decl)
        more = self.targets(decl, HAS_INTERFACE)
        if node is not None and node.node_class.endswith("Type"):
            more += self.targets(decl, HAS_SUBTYPE, forward=False)
        else:
            more += self.targets(decl, HAS_TYPE_DEFINITION)
        for other in more:
            hit = self.find(other, name, seen)
            if hit is not None:
                return hit
        return None


def _key(text: str, uris: list[str], aliases: dict[str, str]) -> Key:
    text = aliases.get(text, text)
    if text.startswith("ns="):
        ns, ident = text.split(";", 1)
        return uris[int(ns[3:])], ident
    return UA_URI, text


def load_reference() -> Reference:
    ref = Reference()
    for name in FILES:
        root = ET.parse(DATA / name).getroot()
        uris = [UA_URI] + [u.text for u in root.find(X + "NamespaceUris")]
        aliases = {a.get("Alias"): a.text for a in root.iter(X + "Alias")}
        for e in root:
            nid = e.get("NodeId")
            if nid is None:
                continue
            key = _key(nid, uris, aliases)
            bn = e.get("BrowseName")
            ns, _, bname = bn.partition(":")
            if not ns.isdigit() or not _:
                ns, bname = "0", bn
            dt = e.get("DataType")
            defn = e.find(X + "Definition")
            ref.nodes[key] = XNode(
                node_class=e.tag[len(X):],
                browse_name=(uris[int(ns)], bname),
                data_type=_key(dt, uris, aliases) if dt else None,
                value_rank=int(e.get("ValueRank", "-1")),
                fields=[(f.get("Name"), int(f.get("Value", "0"))) for f in defn]
                if defn is not None else [],
            )
            for r in e.find(X + "References"):
                ref.add_ref(key, _key(r.get("ReferenceType"), uris, aliases),
                            r.get("IsForward", "true") != "false", _key(r.text, uris, aliases))
    return ref


class Ours:
    """Reads our server through a client, keyed like the reference."""

    def __init__(self, client: Client, uris: list[str]) -> None:
        self.c = client
        self.uris = uris

    def key(self, nid: ua.NodeId) -> Key:
        ident = nid.Identifier
        kind = "i" if isinstance(ident, int) else "s"
        return self.uris[nid.NamespaceIndex], f"{kind}={ident}"

    async def refs(self, nid: ua.NodeId) -> set[tuple[Key, bool, Key]]:
        node = self.c.get_node(nid)
        out = set()
        for d in await node.get_references(refs=ua.ObjectIds.References,
                                           direction=ua.BrowseDirection.Both):
            out.add((self.key(d.ReferenceTypeId), bool(d.IsForward), self.key(d.NodeId)))
        return out

    async def attrs(self, nid: ua.NodeId) -> XNode:
        node = self.c.get_node(nid)
        nc = (await node.read_node_class()).name
        bn = await node.read_browse_name()
        dt, rank, fields = None, -1, []
        if nc in ("Variable", "VariableType"):
            dt = self.key(await node.read_data_type())
            rank = await node.read_value_rank()
        if nc == "DataType":
            try:
                d = (await node.read_attribute(ua.AttributeIds.DataTypeDefinition)).Value.Value
                fields = [(f.Name, int(f.Value)) for f in d.Fields]
            except ua.UaStatusCodeError:
                fields = []
        return XNode("UA" + nc, (self.uris[bn.NamespaceIndex], bn.Name), dt, rank, fields)


def _read_server(heads=None):
    """Every node of a started server in the companion and our namespaces, read by a client."""
    async def go():
        srv = OpcUaServer("opc.tcp://127.0.0.1:0", knives=4, heads=heads,
                          identification={"Manufacturer": "ACME", "SerialNumber": "1"})
        await srv.start()
        try:
            aspace = srv._server.iserver.aspace._nodes  # asyncua's node table: every node we made
            async with Client(srv.endpoint) as c:
                uris = await c.get_namespace_array()
                ours = Ours(c, uris)
                official = [n for n in aspace if uris[n.NamespaceIndex] in COMPANION]
                own = [n for n in aspace if uris[n.NamespaceIndex] == OWN_URI]
                data = {}
                for nid in official + own:
                    data[ours.key(nid)] = (await ours.attrs(nid), await ours.refs(nid))
                machine = ours.key(srv.nodes.machine.nodeid)
                return data, machine
        finally:
            await srv.stop()
    return asyncio.run(go())


@pytest.fixture(scope="module")
def reference():
    return load_reference()


@pytest.fixture(scope="module")
def checked(reference):
    data, machine = _read_server()
    return reference, data, machine


HEADS = [{"name": "bottom", "face": "bottom", "knives": 4},
         {"name": "top", "face": "top", "knives": 6}]


@pytest.fixture(scope="module")
def checked_heads(reference):
    data, machine = _read_server(HEADS)
    return reference, data, machine


@pytest.mark.parametrize("which", ["checked", "checked_heads"])
def test_official_nodes_match_the_nodesets(which, request):
    ref, data, _ = request.getfixturevalue(which)
    official = {k: v for k, v in data.items() if k[0] in COMPANION}
    assert len(official) >= 15  # types, enumerations, event fields, the Machines folder
    for key, (node, refs) in official.items():
        x = ref.nodes.get(key)
        assert x is not None, f"{key} is not in the official nodesets"
        assert node.node_class == x.node_class, key
        assert node.browse_name == x.browse_name, key
        if x.node_class == "UAVariable":
            assert node.data_type == x.data_type, key
            assert node.value_rank == x.value_rank, key
        if x.fields:
            assert node.fields == x.fields, key
        for rtype, forward, target in refs:
            if target[0] in (UA_URI, *COMPANION):
                assert (rtype, forward, target) in ref.refs.get(key, set()), \
                    f"{key}: reference {rtype} {'->' if forward else '<-'} {target} not official"


def _children(data, key):
    _, refs = data[key]
    return [(rtype[1], dst) for rtype, fwd, dst in refs
            if fwd and rtype[0] == UA_URI and rtype[1] in HIERARCHICAL and dst in data]


def _walk(ref, data, stack) -> int:
    """Check every companion-namespace node below each ``(ours, declaration)`` of ``stack``
    against its declaration; the number of nodes checked."""
    checked_count = 0
    while stack:
        ours_key, decl_key = stack.pop()
        present = set()
        for rtype, child in _children(data, ours_key):
            node, crefs = data[child]
            if node.browse_name[0] not in COMPANION:
                continue  # ours (ManufacturerSpecific's variables, the heads)
            hit = ref.find(decl_key, node.browse_name)
            assert hit is not None, f"{node.browse_name} has no declaration below {decl_key}"
            decl_rtype, decl = hit
            present.add(node.browse_name)
            _matches(ref, node, crefs, rtype, decl, decl_rtype)
            checked_count += 1
            stack.append((child, decl))
        if decl_key == (WW_URI, "i=2"):
            continue
        for _, dchild in ref.children(decl_key):
            rules = ref.targets(dchild, HAS_MODELLING_RULE)
            if MANDATORY in rules:
                assert ref.nodes[dchild].browse_name in present, \
                    f"mandatory {ref.nodes[dchild].browse_name} missing below {decl_key}"
    return checked_count


def _matches(ref, node, crefs, rtype, decl, decl_rtype) -> None:
    """One instance node against its declaration: reference, class, type, data type, interfaces."""
    x = ref.nodes[decl]
    where = f"{node.browse_name[1]} (declared as {decl})"
    assert rtype == decl_rtype, where
    assert node.node_class == x.node_class, where
    td = [d for t, f, d in crefs if t == (UA_URI, HAS_TYPE_DEFINITION) and f]
    assert td == ref.targets(decl, HAS_TYPE_DEFINITION), where
    if x.node_class == "UAVariable":
        assert node.data_type == x.data_type, where
    ifaces = {d for t, f, d in crefs if t == (UA_URI, HAS_INTERFACE) and f}
    assert ifaces == set(ref.targets(decl, HAS_INTERFACE)), where


def test_machine_instance_matches_its_declarations(checked):
    ref, data, machine = checked
    _, mrefs = data[machine]
    assert ((UA_URI, HAS_TYPE_DEFINITION), True, (WW_URI, "i=2")) in mrefs
    assert any(t == (UA_URI, "i=35") and not f and d == (MACHINERY_URI, "i=1001")
               for t, f, d in mrefs), "the machine is organised under Machines"
    checked_count = _walk(ref, data, [(machine, (WW_URI, "i=2"))])
    # Identification + its 6 mandatory properties, State, Machine, Overview + 2, Flags, Values,
    # their variables, Events, ManufacturerSpecific
    assert checked_count == 1 + 6 + 3 + 2 + 2 + len(FLAG_NAMES) + len(VALUE_NAMES) + 2


SUBUNIT = (WW_URI, "i=5036")
"""``WwMachineType/State/SubUnits/<SubUnit>``: the placeholder each head instantiates."""


def test_moulder_heads_are_subunits_matching_their_declaration(checked_heads):
    ref, data, machine = checked_heads
    # the machine as before, plus State/SubUnits (declared, IWwSubUnitsType)
    unit = 1 + 2 + 2 + len(FLAG_NAMES) + len(VALUE_NAMES)  # Overview + 2, Flags, Values, vars
    # Identification + 6, State, Machine and its unit, Events, ManufacturerSpecific, SubUnits
    assert _walk(ref, data, [(machine, (WW_URI, "i=2"))]) == 1 + 6 + 2 + unit + 2 + 1
    subunits = [k for k, (n, _) in data.items() if n.browse_name == (WW_URI, "SubUnits")]
    assert len(subunits) == 1
    heads = [(c, data[c][0].browse_name) for r, c in _children(data, subunits[0])]
    assert sorted(name for _, name in heads) == [(OWN_URI, "bottom"), (OWN_URI, "top")]
    x = ref.nodes[SUBUNIT]
    assert ref.targets(SUBUNIT, HAS_MODELLING_RULE) == [(UA_URI, "i=11510")]  # placeholder
    for head, _ in heads:
        node, crefs = data[head]
        _matches(ref, node, crefs, "i=47", SUBUNIT, "i=47")  # HasComponent of SubUnits
        assert x.browse_name == (WW_URI, "<SubUnit>")
        # each head: its Overview (mandatory), Flags and Values, as the declaration says
        assert _walk(ref, data, [(head, SUBUNIT)]) == unit
