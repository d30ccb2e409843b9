"""Running the simulated machine.

The driver, the runner of planer sim and its wiring.
"""
