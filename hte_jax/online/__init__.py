"""Online damage recovery: Gaussian processes, maze, planning, and the RTE / HTE / APROL loops."""
