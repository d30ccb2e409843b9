"""Fieldbus and hand-off protocols shared by the simulator and the service.

The sans-I/O codecs (PLC register map, piezo CAN frames, image-pair metadata) and the two thin
transports both sides open the same way (CAN buses, the spool folder).
"""
