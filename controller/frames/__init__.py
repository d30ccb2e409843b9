"""Where image pairs come from: frame sources, the spool watch, the GenICam camera path."""
