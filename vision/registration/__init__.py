"""Registration of the two images of a pair, and the measurement's own checks on it."""
