"""Shared, sans-I/O fieldbus protocol definitions: the PLC register map and the piezo CAN frames."""
