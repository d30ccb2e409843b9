"""The address space: the machine instance and the few companion-specification types it uses.

The subset of DI / Machinery / Woodworking types is built in code with the official NodeIds,
BrowseNames, TypeDefinitions and DataTypes of the published nodesets (DI 1.05, Machinery 1.04,
Woodworking 1.02); the machine is a ``WwMachineType`` instance under ``Objects/Machines``.

asyncua's ``import_xml`` of the full chain fails (Machinery/Jobs), and the nodesets are not part
of the product: the few types are declared here and
``tests/controller/opcua/test_opcua_conformance.py`` checks
every node against the official XML files.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from asyncua import Server, ua
from asyncua.common.node import Node
from asyncua.common.structures104 import new_enum

from controller.opcua.view import FLAG_NAMES, MANUFACTURER_INITIAL, MANUFACTURER_NAMES, VALUE_NAMES

__all__ = [
    "DI_URI",
    "IDENTIFICATION_FIELDS",
    "MACHINERY_URI",
    "MANDATORY_IDENTIFICATION",
    "OWN_URI",
    "WW_URI",
    "MachineNodes",
    "build_address_space",
]

DI_URI = "http://opcfoundation.org/UA/DI/"
MACHINERY_URI = "http://opcfoundation.org/UA/Machinery/"
WW_URI = "http://opcfoundation.org/UA/Woodworking/"
OWN_URI = "urn:smart-planer:machine"
"""Our namespace: the machine instance and the ``ManufacturerSpecific`` variables."""

# official numeric NodeIds (i=...) in their namespaces
WW_MACHINE_TYPE = 2
WW_UNIT_MODE_ENUM = 20
WW_UNIT_STATE_ENUM = 21
WW_EVENT_CATEGORY_ENUM = 3004
WW_BASE_EVENT_TYPE = 13
WW_EVENTS_DISPATCHER_TYPE = 15
WW_EVENT_PROPS = {  # WwBaseEventType's properties: name -> (i, data type, value rank)
    "MessageId": (256, ua.VariantType.String, -1),
    "MessageName": (257, ua.VariantType.String, -1),
    "PathParts": (258, ua.VariantType.String, 1),
    "Group": (259, ua.VariantType.String, -1),
    "EventCategory": (6056, None, -1),
}
WW_INTERFACES = {  # the interfaces the State objects implement (HasInterface)
    "State": (8, "IWwStateType"),
    "State/Machine": (6, "IWwBaseStateType"),
    "State/Machine/Flags": (4, "IWwUnitFlagsType"),
    "State/Machine/Overview": (5, "IWwUnitOverviewType"),
    "State/Machine/Values": (1006, "IWwUnitValuesType"),
}
HAS_INTERFACE = 17603
BASE_INTERFACE_TYPE = 17602
WW_ENUM_VALUES = {"mode": 123, "state": 128, "category": 6103}  # their EnumValues properties
MACHINERY_MACHINES = 1001
MACHINERY_ITEM_IDENTIFICATION_TYPE = 1004
MACHINERY_MACHINE_IDENTIFICATION_TYPE = 1012
DI_FUNCTIONAL_GROUP_TYPE = 1005
BASE_ANALOG_TYPE = 15318  # ns=0

IDENTIFICATION_FIELDS: Mapping[str, tuple[str, ua.VariantType]] = {
    # TOML key -> (namespace of the BrowseName: "di" | "machinery", data type)
    "Manufacturer": ("di", ua.VariantType.LocalizedText),
    "Model": ("di", ua.VariantType.LocalizedText),
    "SerialNumber": ("di", ua.VariantType.String),
    "ProductInstanceUri": ("di", ua.VariantType.String),
    "DeviceClass": ("di", ua.VariantType.String),
    "YearOfConstruction": ("machinery", ua.VariantType.UInt16),
    "MonthOfConstruction": ("machinery", ua.VariantType.Byte),
    "ManufacturerUri": ("di", ua.VariantType.String),
    "ProductCode": ("di", ua.VariantType.String),
    "HardwareRevision": ("di", ua.VariantType.String),
    "SoftwareRevision": ("di", ua.VariantType.String),
    "AssetId": ("di", ua.VariantType.String),
    "ComponentName": ("di", ua.VariantType.LocalizedText),
    "Location": ("machinery", ua.VariantType.String),
}
"""The ``Identification`` properties we serve (``[identification]`` keys in machine.toml)."""
MANDATORY_IDENTIFICATION = (
    "Manufacturer", "Model", "SerialNumber", "ProductInstanceUri", "DeviceClass",
    "YearOfConstruction",
)
"""Mandatory in ``WwMachineType/Identification``: always served (defaults when not configured)."""

_MANUFACTURER_TYPES = {
    "Double": (ua.VariantType.Double, -1), "Double[]": (ua.VariantType.Double, 1),
    "String": (ua.VariantType.String, -1), "Boolean": (ua.VariantType.Boolean, -1),
    "Int64": (ua.VariantType.Int64, -1), "String[]": (ua.VariantType.String, 1),
}


@dataclass
class MachineNodes:
    """The nodes the server writes: the machine object, its variables by path, the event parts.

    Attributes
    ----------
    machine : Node
        The ``WwMachineType`` instance.
    variables : dict of str to Node
        Variables by path below the machine (``"State/Machine/Flags/Error"``).
    variant_types : dict of str to ua.VariantType
        The data type each variable's value is written with.
    events_node : Node
        ``Events`` (``WwEventsDispatcherType``): the event notifier of the machine's events.
    event_type : Node
        ``WwBaseEventType``.
    ns : dict of str to int
        Namespace indices: ``"di"``, ``"machinery"``, ``"ww"``, ``"own"``.
    machine_name : str
        The machine's BrowseName (and the prefix of our NodeIds).
    types : dict
        The declared type nodes (``interfaces``, ``state_enum``, ...).
    state, manufacturer : Node or None
        ``State`` and ``ManufacturerSpecific`` (the heads are added below them).
    heads : list of str
        The heads built (:func:`controller.opcua.heads_nodes.build_heads`), in order.
    """

    machine: Node
    variables: dict[str, Node] = field(default_factory=dict)
    variant_types: dict[str, ua.VariantType] = field(default_factory=dict)
    events_node: Node | None = None
    event_type: Node | None = None
    ns: dict[str, int] = field(default_factory=dict)
    machine_name: str = "SmartPlaner"
    types: dict[str, Any] = field(default_factory=dict)
    state: Node | None = None
    manufacturer: Node | None = None
    heads: list[str] = field(default_factory=list)


def _own_id(machine_name: str, path: str, own: int) -> ua.NodeId:
    return ua.NodeId(f"{machine_name}.{path.replace('/', '.')}", own)


def _qn(name: str, idx: int) -> ua.QualifiedName:
    return ua.QualifiedName(name, idx)


async def _retype(node: Node, type_id: ua.NodeId) -> None:
    """Replace a node's ``HasTypeDefinition`` (asyncua creates BaseDataVariableType)."""
    old = await node.read_type_definition()
    await node.delete_reference(old, ua.ObjectIds.HasTypeDefinition, forward=True)
    await node.add_reference(type_id, ua.ObjectIds.HasTypeDefinition)


async def _enum_values(enum_node: Node, prop_id: ua.NodeId) -> None:
    """The ``EnumValues`` property generic clients show the names with (official NodeId)."""
    definition = await enum_node.read_data_type_definition()
    values = [ua.EnumValueType(Value=f.Value, DisplayName=ua.LocalizedText(f.Name),
                               Description=ua.LocalizedText(f.Name))
              for f in definition.Fields]
    prop = await enum_node.add_property(prop_id, ua.QualifiedName("EnumValues", 0),
                                        ua.Variant(values, ua.VariantType.ExtensionObject),
                                        datatype=ua.NodeId(ua.ObjectIds.EnumValueType))
    await prop.write_value_rank(1)
    await prop.write_array_dimensions([len(values)])


async def _types(server: Server, ns: Mapping[str, int]) -> dict[str, Node]:
    """Declare the type nodes of the subset under their official NodeIds."""
    di, ma, ww = ns["di"], ns["machinery"], ns["ww"]
    base_object = server.get_node(ua.NodeId(ua.ObjectIds.BaseObjectType))
    folder = server.get_node(ua.NodeId(ua.ObjectIds.FolderType))
    fg = await folder.add_object_type(ua.NodeId(DI_FUNCTIONAL_GROUP_TYPE, di),
                                      _qn("FunctionalGroupType", di))
    item_id = await fg.add_object_type(ua.NodeId(MACHINERY_ITEM_IDENTIFICATION_TYPE, ma),
                                       _qn("MachineryItemIdentificationType", ma))
    machine_id = await item_id.add_object_type(
        ua.NodeId(MACHINERY_MACHINE_IDENTIFICATION_TYPE, ma),
        _qn("MachineIdentificationType", ma))
    ww_machine = await base_object.add_object_type(ua.NodeId(WW_MACHINE_TYPE, ww),
                                                   _qn("WwMachineType", ww))
    dispatcher = await base_object.add_object_type(ua.NodeId(WW_EVENTS_DISPATCHER_TYPE, ww),
                                                   _qn("WwEventsDispatcherType", ww))
    state_enum = await new_enum(server, ua.NodeId(WW_UNIT_STATE_ENUM, ww),
                                _qn("WwUnitStateEnumeration", ww),
                                ["OFFLINE", "STANDBY", "READY", "WORKING", "ERROR"])
    mode_enum = await new_enum(server, ua.NodeId(WW_UNIT_MODE_ENUM, ww),
                               _qn("WwUnitModeEnumeration", ww),
                               ["OTHER", "AUTOMATIC", "SEMIAUTOMATIC", "MANUAL", "SETUP", "SLEEP"])
    cat_enum = await new_enum(server, ua.NodeId(WW_EVENT_CATEGORY_ENUM, ww),
                              _qn("WwEventCategoryEnumeration", ww),
                              ["OTHER", "DIAGNOSTIC", "INFORMATION", "WARNING", "ALARM", "ERROR"])
    for enum_node, prop_id in ((state_enum, WW_ENUM_VALUES["state"]),
                               (mode_enum, WW_ENUM_VALUES["mode"]),
                               (cat_enum, WW_ENUM_VALUES["category"])):
        await _enum_values(enum_node, ua.NodeId(prop_id, ww))
    base_event = server.get_node(ua.NodeId(ua.ObjectIds.BaseEventType))
    event_type = await base_event.add_object_type(ua.NodeId(WW_BASE_EVENT_TYPE, ww),
                                                  _qn("WwBaseEventType", ww))
    mandatory = server.get_node(ua.NodeId(ua.ObjectIds.ModellingRule_Mandatory))
    optional = server.get_node(ua.NodeId(ua.ObjectIds.ModellingRule_Optional))
    for name, (i, vtype, rank) in WW_EVENT_PROPS.items():
        if vtype is None:
            prop = await event_type.add_property(ua.NodeId(i, ww), _qn(name, ww), 0,
                                                 ua.VariantType.Int32, datatype=cat_enum.nodeid)
        elif rank == 1:
            prop = await event_type.add_property(ua.NodeId(i, ww), _qn(name, ww),
                                                 ua.Variant([], vtype, is_array=True))
            await prop.write_value_rank(1)
        else:
            prop = await event_type.add_property(ua.NodeId(i, ww), _qn(name, ww), "", vtype)
        rule = mandatory if name in ("MessageId", "PathParts", "EventCategory") else optional
        await prop.add_reference(rule.nodeid, ua.ObjectIds.HasModellingRule)
    base_interface = server.get_node(ua.NodeId(BASE_INTERFACE_TYPE))
    interfaces = {
        path: await base_interface.add_object_type(ua.NodeId(i, ww), _qn(name, ww))
        for path, (i, name) in WW_INTERFACES.items()
    }
    return {
        "interfaces": interfaces,
        "machine_identification": machine_id, "ww_machine": ww_machine,
        "dispatcher": dispatcher, "state_enum": state_enum, "mode_enum": mode_enum,
        "event_type": event_type,
    }


def _identification_value(key: str, value: Any, vtype: ua.VariantType) -> ua.Variant:
    if vtype == ua.VariantType.LocalizedText:
        return ua.Variant(ua.LocalizedText(str(value), "en"), vtype)
    if vtype in (ua.VariantType.UInt16, ua.VariantType.Byte):
        return ua.Variant(int(value), vtype)
    return ua.Variant(str(value), vtype)


async def build_address_space(
    server: Server,
    identification: Mapping[str, Any],
    *,
    machine_name: str = "SmartPlaner",
    knives: int = 0,
) -> MachineNodes:
    """Register the namespaces, declare the types and build the machine instance.

    Parameters
    ----------
    server : asyncua.Server
        An initialised (``await server.init()``), not yet started server.
    identification : mapping
        ``Identification`` values by :data:`IDENTIFICATION_FIELDS` key; the mandatory ones
        (:data:`MANDATORY_IDENTIFICATION`) get a placeholder when absent.
    machine_name : str
        BrowseName of the machine object under ``Machines``.
    knives : int
        Number of knives (length of the per-knife arrays before the first measurement).

    Returns
    -------
    MachineNodes
    """
    unknown = set(identification) - set(IDENTIFICATION_FIELDS)
    if unknown:
        raise ValueError(f"identification: unknown keys {sorted(unknown)} "
                         f"(known: {', '.join(IDENTIFICATION_FIELDS)})")
    ns = {
        "di": await server.register_namespace(DI_URI),
        "machinery": await server.register_namespace(MACHINERY_URI),
        "ww": await server.register_namespace(WW_URI),
        "own": await server.register_namespace(OWN_URI),
    }
    types = await _types(server, ns)
    own = ns["own"]
    objects = server.nodes.objects
    machines = await objects.add_folder(ua.NodeId(MACHINERY_MACHINES, ns["machinery"]),
                                        _qn("Machines", ns["machinery"]))
    machine = await machines.add_object(ua.NodeId(machine_name, own), _qn(machine_name, own),
                                        objecttype=types["ww_machine"].nodeid,
                                        instantiate_optional=False)
    nodes = MachineNodes(machine=machine, ns=ns, event_type=types["event_type"],
                         machine_name=machine_name, types=types)

    await _identification(machine, nodes, identification, machine_name, types, ns)
    await _state(machine, nodes, machine_name, types, ns)
    await _events(machine, nodes, machine_name, types, ns)
    await _manufacturer(machine, nodes, machine_name, knives, ns)
    # the server object sees the machine's events too (HasNotifier chain)
    await server.nodes.server.add_reference(machine.nodeid, ua.ObjectIds.HasNotifier)
    return nodes


async def _identification(machine: Node, nodes: MachineNodes,
                          identification: Mapping[str, Any], machine_name: str,
                          types: Mapping[str, Any], ns: Mapping[str, int]) -> None:
    """``Identification``: a DI AddIn of type ``MachineIdentificationType``."""
    own = ns["own"]
    # Identification (DI AddIn of type Machinery MachineIdentificationType)
    ident = await machine.add_object(ua.NodeId(f"{machine_name}.Identification", own),
                                     _qn("Identification", ns["di"]),
                                     objecttype=types["machine_identification"].nodeid,
                                     instantiate_optional=False)
    await machine.delete_reference(ident, ua.ObjectIds.HasComponent, forward=True,
                                   bidirectional=True)
    await machine.add_reference(ident.nodeid, ua.ObjectIds.HasAddIn)
    defaults = {"Manufacturer": "unknown", "Model": "smart-planer", "SerialNumber": "0",
                "ProductInstanceUri": "urn:smart-planer:unknown", "DeviceClass": "planer",
                "YearOfConstruction": 2026}
    values = {**defaults, **dict(identification)}
    for key in IDENTIFICATION_FIELDS:
        if key not in values:
            continue
        where, vtype = IDENTIFICATION_FIELDS[key]
        prop = await ident.add_property(
            ua.NodeId(f"{machine_name}.Identification.{key}", own), _qn(key, ns[where]),
            _identification_value(key, values[key], vtype))
        nodes.variables[f"Identification/{key}"] = prop


async def _state(machine: Node, nodes: MachineNodes, machine_name: str,
                 types: Mapping[str, Any], ns: Mapping[str, int]) -> None:
    """``State/Machine/{Overview, Flags, Values}`` and their interfaces."""
    own, ww = ns["own"], ns["ww"]
    # State/Machine/{Overview, Flags, Values}
    state = await machine.add_object(ua.NodeId(f"{machine_name}.State", own), _qn("State", ww))
    unit = await state.add_object(ua.NodeId(f"{machine_name}.State.Machine", own),
                                  _qn("Machine", ww))
    await build_unit(unit, "State/Machine", nodes, machine_name, types, ns)
    await state.add_reference(types["interfaces"]["State"].nodeid, HAS_INTERFACE)
    nodes.state = state


async def build_unit(unit: Node, base: str, nodes: MachineNodes, machine_name: str,
                     types: Mapping[str, Any], ns: Mapping[str, int]) -> None:
    """A unit's ``Overview``, ``Flags`` and ``Values`` (``IWwBaseStateType``) below ``unit``.

    ``base`` is the unit's path below the machine (``State/Machine``,
    ``State/SubUnits/top``); the variables are registered in ``nodes`` under it.
    """
    own, ww = ns["own"], ns["ww"]

    def nid(path: str) -> ua.NodeId:
        return _own_id(machine_name, path, own)

    overview = await unit.add_object(nid(f"{base}/Overview"), _qn("Overview", ww))
    for name, enum_node in (("CurrentState", types["state_enum"]),
                            ("CurrentMode", types["mode_enum"])):
        path = f"{base}/Overview/{name}"
        var = await overview.add_variable(nid(path), _qn(name, ww), 0,
                                          ua.VariantType.Int32, datatype=enum_node.nodeid)
        nodes.variables[path], nodes.variant_types[path] = var, ua.VariantType.Int32
    flags = await unit.add_object(nid(f"{base}/Flags"), _qn("Flags", ww))
    for name in FLAG_NAMES:
        path = f"{base}/Flags/{name}"
        var = await flags.add_variable(nid(path), _qn(name, ww), False, ua.VariantType.Boolean)
        nodes.variables[path], nodes.variant_types[path] = var, ua.VariantType.Boolean
    vals = await unit.add_object(nid(f"{base}/Values"), _qn("Values", ww))
    analog = ua.NodeId(BASE_ANALOG_TYPE)
    for name in VALUE_NAMES:
        path = f"{base}/Values/{name}"
        vtype = ua.VariantType.Double if name == "FeedSpeed" else ua.VariantType.UInt64
        var = await vals.add_variable(nid(path), _qn(name, ww),
                                      ua.Variant(math.nan if name == "FeedSpeed" else 0, vtype),
                                      varianttype=vtype)
        await _retype(var, analog)
        nodes.variables[path], nodes.variant_types[path] = var, vtype

    for part, node in (("State/Machine", unit), ("State/Machine/Flags", flags),
                       ("State/Machine/Overview", overview), ("State/Machine/Values", vals)):
        await node.add_reference(types["interfaces"][part].nodeid, HAS_INTERFACE)


async def _events(machine: Node, nodes: MachineNodes, machine_name: str,
                  types: Mapping[str, Any], ns: Mapping[str, int]) -> None:
    """``Events``: the notifier of the machine's Woodworking events."""
    own, ww = ns["own"], ns["ww"]
    # Events (WwEventsDispatcherType): the notifier of the machine's Woodworking events
    events = await machine.add_object(ua.NodeId(f"{machine_name}.Events", own), _qn("Events", ww),
                                      objecttype=types["dispatcher"].nodeid)
    await events.write_attribute(ua.AttributeIds.EventNotifier,
                                 ua.DataValue(ua.Variant(1, ua.VariantType.Byte)))
    await machine.write_attribute(ua.AttributeIds.EventNotifier,
                                  ua.DataValue(ua.Variant(1, ua.VariantType.Byte)))
    await machine.add_reference(events.nodeid, ua.ObjectIds.HasNotifier)
    nodes.events_node = events


async def _manufacturer(machine: Node, nodes: MachineNodes, machine_name: str, knives: int,
                        ns: Mapping[str, int]) -> None:
    """``ManufacturerSpecific``: our variables in our namespace."""
    own, ww = ns["own"], ns["ww"]
    # ManufacturerSpecific (FolderType), our variables in our namespace
    ms = await machine.add_object(ua.NodeId(f"{machine_name}.ManufacturerSpecific", own),
                                  _qn("ManufacturerSpecific", ww),
                                  objecttype=ua.NodeId(ua.ObjectIds.FolderType))
    await add_manufacturer_variables(ms, "ManufacturerSpecific", MANUFACTURER_NAMES, nodes,
                                     machine_name, knives, own)
    nodes.manufacturer = ms


async def add_manufacturer_variables(folder: Node, base: str, names: Mapping[str, str],
                                     nodes: MachineNodes, machine_name: str, knives: int,
                                     own: int) -> None:
    """Our variables (``names``: name -> data type) in ``folder``, registered under ``base``."""
    for name, kind in names.items():
        path = f"{base}/{name}"
        vtype, rank = _MANUFACTURER_TYPES[kind]
        if rank == 1:
            init = ua.Variant([math.nan] * knives if vtype == ua.VariantType.Double else [],
                              vtype, is_array=True)
        elif vtype == ua.VariantType.Double:
            init = ua.Variant(math.nan, vtype)
        elif vtype == ua.VariantType.String:
            init = ua.Variant("", vtype)
        elif vtype == ua.VariantType.Boolean:
            init = ua.Variant(False, vtype)
        else:
            init = ua.Variant(MANUFACTURER_INITIAL.get(name, 0), vtype)
        var = await folder.add_variable(_own_id(machine_name, path, own), _qn(name, own), init,
                                        varianttype=vtype)
        if rank == 1:
            await var.write_value_rank(1)
            await var.write_array_dimensions([0])
        nodes.variables[path], nodes.variant_types[path] = var, vtype
