"""Reproducible experiments whose results are written into ``docs/``."""
