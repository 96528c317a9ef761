"""Simulation of the hexapod in MJX: robot model, controllers, damages, batched rollouts."""

from hte_jax.sim.controller import leg_primitive, servo_command, signal_table, target_table
from hte_jax.sim.damage import (DAMAGED_POSE, PAPER_DAMAGES, Damage, DamageModel, damage_mask, make_damage,
                                paper_damage_masks, parse_damage, parse_damages, register_damage)
from hte_jax.sim.env import InvalidReason, SimState, ValidityLimits
from hte_jax.sim.robot import Robot, RobotConfig, load_robot
from hte_jax.sim.rollout import RolloutResult, RolloutSpec, initial_state, rollout, standing_state

__all__ = ["DAMAGED_POSE", "PAPER_DAMAGES", "Damage", "DamageModel", "InvalidReason", "Robot", "RobotConfig",
           "RolloutResult", "RolloutSpec", "SimState", "ValidityLimits", "damage_mask", "initial_state",
           "leg_primitive", "load_robot", "make_damage", "paper_damage_masks", "parse_damage", "parse_damages",
           "register_damage",
           "rollout", "servo_command", "signal_table", "standing_state", "target_table"]
