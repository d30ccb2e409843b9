"""Where image pairs come from.

Frame sources, the spool watch, the GenICam camera path.
"""
