"""The simulated planer as one machine.

The time-stepped model behind the interfaces: the Machine facade, its PLC logic and
register view, fault injection.
"""
