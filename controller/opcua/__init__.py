"""OPC UA server of the machine per OPC 40550 (Woodworking), on DI and Machinery (docs/opcua.md).

``asyncua`` is an optional dependency (the ``opcua`` extra): import
:mod:`controller.opcua.server` only when a server is asked for.
"""
