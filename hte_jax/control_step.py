"""The control step: the servos' 100 Hz, defined once for the simulation, the repertoires and the commands. It
imports nothing, so a command can check its arguments against it before mujoco or OpenGL is loaded."""

STEPS_PER_SECOND = 100  # control steps in one simulated second (`RobotConfig.control_dt` = 1 / this)
