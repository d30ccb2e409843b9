"""Image formation.

Optics, wood, the camera downstream of the cutter, render workers, one-call boards.
"""
