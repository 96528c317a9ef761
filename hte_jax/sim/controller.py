"""Open-loop periodic controllers of the original HTE code (`docs/original_code.md` §2).

Every joint follows a 100-sample periodic signal of period 1 s: a square wave of
duty d and amplitude a, smoothed by a circular Gaussian (sigma = 3 samples, 21 taps),
circularly shifted by phase p, read with a zero-order hold at 100 Hz. All parameters
lie in [0, 1].

* 36-parameter controller: leg L uses params[6L:6L+3] = (a, p, d) for the hip-yaw
  signal s0 and params[6L+3:6L+6] for the vertical signal s1. Joint targets:
  hip = -(pi/8) s0, femur = +(pi/4) s1, tibia = +(pi/4) s1; the femur and tibia axes
  are opposite, so equal targets keep the tibia vertical.
* leg primitive: the 6 parameters of one leg, the other legs held at 0 (standing).
* servo: commanded joint velocity (target - q) / (pi * 0.01), clipped to +-5 rad/s.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.sim.robot import NUM_JOINTS, NUM_LEGS

SAMPLES_PER_PERIOD = 100
PARAMS_PER_SIGNAL = 3
PARAMS_PER_LEG = 6
NUM_PARAMS = NUM_LEGS * PARAMS_PER_LEG  # 36
SMOOTHING_SIGMA = 3.0
SMOOTHING_HALF_WIDTH = 10
HIP_AMPLITUDE = np.pi / 8
VERTICAL_AMPLITUDE = np.pi / 4
SERVO_TIME_CONSTANT = np.pi * 0.01  # commanded velocity = error / this
# floor(100 x) is taken as floor(100 x + FLOOR_GUARD) so that decimal parameters such as
# 0.29 give 29 samples whatever float rounding did to 100 * 0.29 (see docs/design.md).
FLOOR_GUARD = 1e-4


def _smoothing_weights() -> np.ndarray:
    offsets = np.arange(-SMOOTHING_HALF_WIDTH, SMOOTHING_HALF_WIDTH + 1)
    weights = np.exp(-(offsets**2) / (2.0 * SMOOTHING_SIGMA**2))
    return (weights / weights.sum()).astype(np.float32)


_WEIGHTS = _smoothing_weights()
_SAMPLES = np.arange(SAMPLES_PER_PERIOD)
# _WINDOW[j, k] = (j + k - 10) mod 100: the samples averaged into output sample j.
_WINDOW = (_SAMPLES[:, None] + np.arange(-SMOOTHING_HALF_WIDTH, SMOOTHING_HALF_WIDTH + 1)[None, :]) % (
    SAMPLES_PER_PERIOD
)


def _count(x: jax.Array) -> jax.Array:
    """floor(100 x) as int32, guarded against float rounding just below an integer."""
    return jnp.floor(SAMPLES_PER_PERIOD * x + FLOOR_GUARD).astype(jnp.int32)


def signal_table(amplitude: jax.Array, phase: jax.Array, duty: jax.Array) -> jax.Array:
    """One period of the smoothed, shifted square wave.

    Args: scalars amplitude, phase, duty in [0, 1] (batch with vmap).
    Returns: (100,) float32 signal in [-amplitude, amplitude].
    """
    square = jnp.where(_SAMPLES < _count(duty), amplitude, -amplitude).astype(jnp.float32)
    smoothed = square[_WINDOW] @ _WEIGHTS
    return smoothed[(_SAMPLES + _count(phase)) % SAMPLES_PER_PERIOD]


def target_table(params: jax.Array) -> jax.Array:
    """Joint-target table of the 36-parameter controller.

    Args: params (36,) in [0, 1].
    Returns: (100, 18) joint targets in radians, leg-major joint order
    (leg0 hip, femur, tibia, leg1 hip, ...); row k is used during control step k mod 100.
    """
    signals = jax.vmap(signal_table)(*params.reshape(NUM_LEGS * 2, PARAMS_PER_SIGNAL).T)  # (12, 100)
    hip = -HIP_AMPLITUDE * signals[0::2]  # (6, 100)
    vertical = VERTICAL_AMPLITUDE * signals[1::2]
    table = jnp.stack([hip, vertical, vertical], axis=1)  # (6, 3, 100)
    return table.reshape(NUM_JOINTS, SAMPLES_PER_PERIOD).T


def leg_primitive(leg_params: jax.Array, leg: jax.Array) -> jax.Array:
    """Embed one leg's 6 parameters into a 36-parameter controller, other legs at rest.

    Args: leg_params (6,) in [0, 1]; leg: int scalar in 0..5.
    Returns: (36,) parameters, zero (standing pose) for the other five legs.
    """
    rows = jnp.zeros((NUM_LEGS, PARAMS_PER_LEG), leg_params.dtype)
    return rows.at[leg].set(leg_params).reshape(NUM_PARAMS)


def servo_command(target: jax.Array, joint_pos: jax.Array, max_velocity: float) -> jax.Array:
    """Velocity command of the original servo: (target - q) / (pi * 0.01), clipped.

    Args: target, joint_pos (18,) radians. Returns: (18,) rad/s.
    """
    return jnp.clip((target - joint_pos) / SERVO_TIME_CONSTANT, -max_velocity, max_velocity)



def commanded_travel(params: jax.Array) -> jax.Array:
    """How far each leg's joints are asked to move in one period: (..., 36) params -> (..., 6) rad,
    the sum over the leg's three joints of sum_k |target(k + 1) - target(k)| around the period."""
    table = jnp.vectorize(target_table, signature="(p)->(t,j)")(params)  # (..., 100, 18)
    steps = jnp.abs(jnp.roll(table, -1, axis=-2) - table).sum(axis=-2)  # (..., 18)
    return steps.reshape(*steps.shape[:-1], NUM_LEGS, NUM_JOINTS // NUM_LEGS).sum(axis=-1)
