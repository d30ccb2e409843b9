"""plant_sim: the smart planer in software (kinematics, optics, PLC and piezo amplifier)."""
