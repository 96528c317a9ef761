"""Plain NumPy (float64, explicit loops) reference of the original controller, `docs/original_code.md` §2.1.

Written from the specification, independently of hte_jax.sim.controller, to test it.
"""

import math

import numpy as np

N = 100
GUARD = 1e-4  # same documented rounding guard as the library (docs/design.md)


def signal(a: float, p: float, d: float) -> np.ndarray:
    high = math.floor(N * d + GUARD)
    square = [a if j < high else -a for j in range(N)]
    kernel = [math.exp(-(k * k) / (2 * 3.0 * 3.0)) for k in range(-10, 11)]
    total = sum(kernel)
    smoothed = []
    for j in range(N):
        acc = 0.0
        for i, k in enumerate(range(-10, 11)):
            acc += kernel[i] * square[(j + k) % N]
        smoothed.append(acc / total)
    shift = math.floor(N * p + GUARD)
    return np.array([smoothed[(j + shift) % N] for j in range(N)])


def joint_targets(params: np.ndarray) -> np.ndarray:
    """(36,) -> (100, 18): hip -(pi/8) s0, femur and tibia +(pi/4) s1, per leg."""
    out = np.zeros((N, 18))
    for leg in range(6):
        s0 = signal(*params[6 * leg : 6 * leg + 3])
        s1 = signal(*params[6 * leg + 3 : 6 * leg + 6])
        out[:, 3 * leg] = -(math.pi / 8) * s0
        out[:, 3 * leg + 1] = (math.pi / 4) * s1
        out[:, 3 * leg + 2] = (math.pi / 4) * s1
    return out
