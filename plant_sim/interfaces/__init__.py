"""The machine's interfaces.

PLC Modbus server and logic, the amplifier's CAN node, the serving thread.
"""
