"""Videos of HBR or flat skills run 3 s from standing (`python -m experiments.render skills` / `patterns`)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.errors import ConfigError
from hte_jax.hbr.hierarchy import ANY_PATTERN, STEPS_PER_SKILL, execute_skill
from hte_jax.hbr.middle import NUM_PATTERNS
from hte_jax.sim.robot import STEPS_PER_SECOND, RobotConfig
from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state
from hte_jax.viz.camera import Camera
from hte_jax.viz.render import label, open_renderer, render_frames, render_model, tile

SKILL_STEPS = STEPS_PER_SKILL * STEPS_PER_SECOND  # 3 s


def chosen(count: int, filled: int, numbers: list[int] | None = None) -> np.ndarray:
    """Skill numbers: `numbers` if given (each in 0 .. filled - 1), else `count` spread evenly."""
    if numbers is not None:
        picked = np.asarray(numbers, np.int64)
        bad = picked[(picked < 0) | (picked >= filled)]
        if bad.size:
            raise ConfigError(f"skill {int(bad[0])} out of range: the repertoire holds {filled} skills (0 .. {filled - 1})")
        return picked
    if count < 1:
        raise ConfigError(f"--count must be >= 1, got {count}")
    return np.unique(np.linspace(0, filled - 1, min(count, filled)).round().astype(np.int64))


def parse_patterns(text: str) -> np.ndarray:
    """Comma-separated contact patterns (0 .. 63, leg 0 the most significant bit, or "any") (P,) int32."""
    patterns = []
    for item in text.split(","):
        item = item.strip()
        if item == "any":
            patterns.append(ANY_PATTERN)
        elif item.isdigit() and int(item) < NUM_PATTERNS:
            patterns.append(int(item))
        else:
            raise ConfigError(f"unknown contact pattern {item!r}: use 0..{NUM_PATTERNS - 1} or any")
    return np.asarray(patterns, np.int32)


def pattern_label(pattern: int) -> str:
    return "any pattern" if pattern == ANY_PATTERN else f"pattern {pattern} ({pattern:06b})"


@functools.partial(jax.jit, static_argnames=("every",))
def flat_states(robot, params, damage, every: int):
    """qpos (B, SKILL_STEPS / every + 1, 25) of flat controllers `params` (B, P) under `damage` (a (B, 6) leg mask or
    a `Damage` (B, ...))."""
    start = standing_state(robot, damage)
    spec = RolloutSpec(num_steps=SKILL_STEPS, record_contacts=False, record_qpos_every=every)
    result = rollout(robot, params, damage, start, spec)
    return jnp.concatenate([result.qpos, result.final_state.qpos[:, None]], axis=1)


@functools.partial(jax.jit, static_argnames=("every",))
def hbr_states(robot, hbr, genotypes, damage, every: int, patterns=None):
    """qpos (B, SKILL_STEPS / every + 1, 25) of HBR skills (B, G) under `damage` (a (B, 6) leg mask or a `Damage`
    (B, ...)), `patterns` (B, 3) held."""
    result = execute_skill(robot, hbr, genotypes, standing_state(robot, damage), damage, patterns, record_every=every)
    steps = jnp.swapaxes(result.steps.qpos, 0, 1)  # (B, 3, F, 25)
    return jnp.concatenate([steps.reshape(steps.shape[0], -1, steps.shape[-1]), result.state.qpos[:, None]], axis=1)


def render_grid(states: np.ndarray, damage, config: RobotConfig, camera: Camera, width: int, height: int,
                columns: int, labels: list[str] | None = None, progress=None) -> np.ndarray:
    """Frames (T, rows * height, columns * width, 3) uint8: clips `states` (N, T, 25) of robots under `damage` (a (6,)
    leg mask or an unbatched `Damage`: `render.render_model`), damaged legs red, tiled."""
    model = render_model(config, damage)
    renderer = open_renderer(model, width, height)
    try:
        clips = [render_frames(model, qpos, renderer, camera, progress) for qpos in states]
    finally:
        renderer.close()
    if labels is not None:
        clips = [label(clip, text) for clip, text in zip(clips, labels)]
    return tile(clips, min(columns, len(clips)))
