"""The machine model: spindle, piezo, feed drive, surface kinematics, the cut's record, faults."""
