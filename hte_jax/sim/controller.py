"""Open-loop periodic controllers of the original HTE code (`docs/original_code.md` §2): every joint follows a 1 s,
100-sample square wave (amplitude a, duty d) smoothed by a circular Gaussian (sigma 3 samples, 21 taps), shifted
by phase p, all in [0, 1]. Leg L's params[6L:6L+3] = (a, p, d) drive hip = -(pi/8) s0, params[6L+3:6L+6]
femur = tibia = (pi/4) s1 (opposite axes: the tibia stays vertical)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.sim.robot import NUM_JOINTS, NUM_LEGS, STEPS_PER_SECOND

SAMPLES_PER_PERIOD = STEPS_PER_SECOND  # a gait's period is one second
PARAMS_PER_SIGNAL = 3
PARAMS_PER_LEG = 6
NUM_PARAMS = NUM_LEGS * PARAMS_PER_LEG  # 36
SMOOTHING_SIGMA = 3.0
SMOOTHING_HALF_WIDTH = 10
HIP_AMPLITUDE = np.pi / 8
VERTICAL_AMPLITUDE = np.pi / 4
SERVO_TIME_CONSTANT = np.pi * 0.01  # commanded velocity = error / this
# floor(100 x + FLOOR_GUARD): 0.29 gives 29 samples whatever rounding did to 100 * 0.29 (docs/design.md).
FLOOR_GUARD = 1e-4
_OFFSETS = np.arange(-SMOOTHING_HALF_WIDTH, SMOOTHING_HALF_WIDTH + 1)
_GAUSSIAN = np.exp(-(_OFFSETS**2) / (2.0 * SMOOTHING_SIGMA**2))
_WEIGHTS = (_GAUSSIAN / _GAUSSIAN.sum()).astype(np.float32)
_SAMPLES = np.arange(SAMPLES_PER_PERIOD)
_WINDOW = (_SAMPLES[:, None] + _OFFSETS[None, :]) % SAMPLES_PER_PERIOD  # [j, k] = (j + k - 10) mod 100: averaged into j


def _count(x: jax.Array) -> jax.Array:
    """floor(100 x) as int32, guarded against float rounding just below an integer."""
    return jnp.floor(SAMPLES_PER_PERIOD * x + FLOOR_GUARD).astype(jnp.int32)


def signal_table(amplitude: jax.Array, phase: jax.Array, duty: jax.Array) -> jax.Array:
    """(100,) float32: one period of the smoothed, shifted square wave of scalars in [0, 1] (vmap to batch)."""
    square = jnp.where(_SAMPLES < _count(duty), amplitude, -amplitude).astype(jnp.float32)
    smoothed = square[_WINDOW] @ _WEIGHTS
    return smoothed[(_SAMPLES + _count(phase)) % SAMPLES_PER_PERIOD]


def target_table(params: jax.Array) -> jax.Array:
    """(100, 18) joint targets (rad, leg-major) of params (36,) in [0, 1], row k for control step k mod 100."""
    signals = jax.vmap(signal_table)(*params.reshape(NUM_LEGS * 2, PARAMS_PER_SIGNAL).T)  # (12, 100)
    hip = -HIP_AMPLITUDE * signals[0::2]  # (6, 100)
    vertical = VERTICAL_AMPLITUDE * signals[1::2]
    table = jnp.stack([hip, vertical, vertical], axis=1)  # (6, 3, 100)
    return table.reshape(NUM_JOINTS, SAMPLES_PER_PERIOD).T


def leg_primitive(leg_params: jax.Array, leg: jax.Array) -> jax.Array:
    """(36,) controller of leg `leg` (int in 0..5) with leg_params (6,), the other legs at 0 (standing)."""
    rows = jnp.zeros((NUM_LEGS, PARAMS_PER_LEG), leg_params.dtype)
    return rows.at[leg].set(leg_params).reshape(NUM_PARAMS)


def servo_command(target: jax.Array, joint_pos: jax.Array, max_velocity: float, xp=jnp) -> jax.Array:
    """(18,) rad/s command of the original servo: (target - joint_pos) / (pi * 0.01), clipped (rad in; jax or NumPy)."""
    return xp.clip((target - joint_pos) / SERVO_TIME_CONSTANT, -max_velocity, max_velocity)


def commanded_travel(params: jax.Array) -> jax.Array:
    """(..., 36) params -> (..., 6): each leg's commanded joint travel per period, sum_k |target(k+1) - target(k)|."""
    table = jnp.vectorize(target_table, signature="(p)->(t,j)")(params)  # (..., 100, 18)
    steps = jnp.abs(jnp.roll(table, -1, axis=-2) - table).sum(axis=-2)  # (..., 18)
    return steps.reshape(*steps.shape[:-1], NUM_LEGS, NUM_JOINTS // NUM_LEGS).sum(axis=-1)
