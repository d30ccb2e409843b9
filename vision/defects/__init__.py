"""Planing defects.

The 2-D surface map of a pair, the detectors, the ASTM D1666 grade.
"""
