"""Hierarchical behavioural repertoire: leg primitives, body motions, skills, and their execution."""

from hte_jax.hbr.analysis import hbr_statistics, pattern_histogram
from hte_jax.hbr.bottom import BottomTask, bottom_spec, evaluate_bottom
from hte_jax.hbr.hierarchy import (ANY_PATTERN, HBR, STEPS_PER_SKILL, SkillResult, StepResult, execute_skill,
                                   execute_step, select_middle, skill_waypoints)
from hte_jax.hbr.modulation import Modulation, modulate
from hte_jax.hbr.middle import (MiddleTask, evaluate_middle, leg_controllers, middle_spec, nearest_index, pattern_bits,
                                pattern_code)
from hte_jax.hbr.store import load_hbr, save_hbr, shipped_hbr_path
from hte_jax.hbr.top import TopTask, evaluate_top, top_spec
from hte_jax.hbr.training import PRESETS, HBRConfig, LayerSchedule, preset, train_hbr, with_overrides

__all__ = ["ANY_PATTERN", "HBR", "PRESETS", "STEPS_PER_SKILL", "BottomTask", "HBRConfig", "LayerSchedule",
           "MiddleTask", "Modulation", "SkillResult", "StepResult", "TopTask", "bottom_spec", "evaluate_bottom",
           "evaluate_middle", "evaluate_top", "execute_skill", "execute_step", "hbr_statistics", "leg_controllers",
           "load_hbr", "middle_spec", "modulate", "nearest_index", "pattern_bits", "pattern_code", "pattern_histogram",
           "preset", "save_hbr", "select_middle", "shipped_hbr_path", "skill_waypoints", "top_spec", "train_hbr",
           "with_overrides"]
