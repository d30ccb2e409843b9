"""plant_sim: the smart planing machine in software (kinematics, optics, PLC and piezo amplifier)."""
