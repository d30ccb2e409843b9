"""The machine's buses.

The PLC's Modbus TCP client and the piezo amplifier's CAN client, with their pure protocol
types.
"""
