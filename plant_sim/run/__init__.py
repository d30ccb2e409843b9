"""Running the simulated machine: the driver, the runner of planer sim and its wiring."""
