"""Online damage recovery: GPs, the maze, MCTS, the pattern rules and variants (RTE, HTE, APROL),
batched reset-free episodes in MJX, and episodes on a robot driven through an executor."""

from hte_jax.online.episode import AdaptationConfig, Episodes, run_episodes, run_together, start_episodes
from hte_jax.online.evaluation import (PRESETS, PROTOCOLS, EvalConfig, load_skills, preset, run_batch, run_batches,
                                      summarise)
from hte_jax.online.external import Executor, MujocoExecutor, Seconds, run_episode
from hte_jax.online.gp import HTE_KERNEL, RTE_KERNEL, GPData, Kernel, add_observation, empty_gp, posterior
from hte_jax.online.maze import PAPER_MAZE, Maze, load_maze
from hte_jax.online.mcts import PlannerConfig
from hte_jax.online.rules import (AnyPattern, GpUcb, Oracle, PatternRule, RandomPattern, SensedLegs, StepContext,
                                  StepObservation)
from hte_jax.online.skills import Skills, flat_skills, hbr_skills
from hte_jax.online.variants import VARIANTS, Variant, add_variant, variant

__all__ = ["HTE_KERNEL", "PAPER_MAZE", "PRESETS", "PROTOCOLS", "RTE_KERNEL", "VARIANTS", "AdaptationConfig",
           "AnyPattern", "Episodes", "EvalConfig", "Executor", "GPData", "GpUcb", "Kernel", "Maze", "MujocoExecutor",
           "Oracle", "PatternRule", "PlannerConfig", "RandomPattern", "Seconds", "SensedLegs", "Skills", "StepContext",
           "StepObservation", "Variant", "add_observation", "add_variant", "empty_gp", "flat_skills", "hbr_skills",
           "load_maze", "load_skills", "posterior", "preset", "run_batch", "run_batches", "run_episode", "run_episodes",
           "run_together", "start_episodes", "summarise", "variant"]
