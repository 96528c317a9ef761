"""Seeing the robot: rendering recorded states to frames and videos."""
