"""Calibration of the camera and the rig.

Lens correction, illumination correction, self-calibration from the knife kinematics.
"""
