"""A moulder's heads in the address space: the machine's units as OPC 40550 models them.

``WwMachineType/State`` (``IWwStateType``, Woodworking ``i=8``) has the optional ``SubUnits``
(Woodworking ``i=5031``, implementing ``IWwSubUnitsType`` ``i=7``): one ``<SubUnit>`` object
per unit (the placeholder ``i=5036``, implementing ``IWwBaseStateType`` ``i=6``: ``Overview``,
``Flags``, ``Values``). Each head is one: ``State/SubUnits/<head>``, its BrowseName the head's
name in our namespace, with its ``ManufacturerSpecific`` folder (ours) beside the standard
parts. The machine's ``ManufacturerSpecific`` gains ``Heads`` and ``LimitingHeads``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from asyncua import Server, ua

from controller.opcua.heads_view import (
    HEAD_MANUFACTURER_NAMES,
    MOULDER_MANUFACTURER_NAMES,
    SUBUNITS,
)
from controller.opcua.nodes import (
    BASE_INTERFACE_TYPE,
    HAS_INTERFACE,
    MachineNodes,
    _own_id,
    _qn,
    add_manufacturer_variables,
    build_unit,
)

__all__ = ["WW_SUBUNITS_INTERFACE", "build_heads"]

WW_SUBUNITS_INTERFACE = 7
"""``IWwSubUnitsType`` (Woodworking ``i=7``): the interface of ``State/SubUnits``."""


async def build_heads(server: Server, nodes: MachineNodes,
                      heads: Sequence[Mapping[str, Any]]) -> None:
    """Add the heads below ``State/SubUnits`` (once; a second call adds only new heads).

    Parameters
    ----------
    server : asyncua.Server
        The server whose address space :func:`~controller.opcua.nodes.build_address_space`
        built (``nodes``).
    nodes : MachineNodes
        Its nodes; the heads' variables are registered in it under
        ``State/SubUnits/<head>/...``.
    heads : sequence of mapping
        The heads in order (``name``, ``knives``: the per-knife arrays' initial length).
    """
    if nodes.state is None or nodes.manufacturer is None:
        raise ValueError("build_heads needs an address space from build_address_space")
    ns, name = nodes.ns, nodes.machine_name
    own, ww = ns["own"], ns["ww"]
    subunits = nodes.types.get("subunits_node")
    if subunits is None:
        base_interface = server.get_node(ua.NodeId(BASE_INTERFACE_TYPE))
        iface = await base_interface.add_object_type(ua.NodeId(WW_SUBUNITS_INTERFACE, ww),
                                                     _qn("IWwSubUnitsType", ww))
        subunits = await nodes.state.add_object(_own_id(name, SUBUNITS, own),
                                                _qn("SubUnits", ww))
        await subunits.add_reference(iface.nodeid, HAS_INTERFACE)
        nodes.types["subunits_node"] = subunits
        await add_manufacturer_variables(nodes.manufacturer, "ManufacturerSpecific",
                                         MOULDER_MANUFACTURER_NAMES, nodes, name, 0, own)
    for head in heads:
        head_name = str(head["name"])
        if head_name in nodes.heads:
            continue
        base = f"{SUBUNITS}/{head_name}"
        unit = await subunits.add_object(_own_id(name, base, own), _qn(head_name, own))
        await build_unit(unit, base, nodes, name, nodes.types, ns)
        ms = await unit.add_object(_own_id(name, f"{base}/ManufacturerSpecific", own),
                                   _qn("ManufacturerSpecific", own),
                                   objecttype=ua.NodeId(ua.ObjectIds.FolderType))
        knives = head.get("knives")
        await add_manufacturer_variables(ms, f"{base}/ManufacturerSpecific",
                                         HEAD_MANUFACTURER_NAMES, nodes, name,
                                         int(knives) if isinstance(knives, int) else 0, own)
        nodes.heads.append(head_name)
