"""The machine model.

Spindle, piezo, feed drive, surface kinematics, the cut's record, faults.
"""
