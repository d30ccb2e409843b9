"""The machine's buses: the PLC's Modbus TCP client and the piezo amplifier's CAN client, with their pure protocol types."""
