"""The kernel fit: the masked log marginal likelihood against a float64 NumPy formula (padded and
full ring buffers, both kernel kinds), and Adam recovering the length-scale of data drawn from a
known GP."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize

from hte_jax.online.gp import HTE_KERNEL, RTE_KERNEL, Kernel, empty_gp
from hte_jax.online.gp_fit import fit_kernel, kernel_of, kernel_params, log_marginal_likelihood
from tests.test_gp import _fill, _numpy_kernel


def _numpy_lml(kernel, x, y, prior):
    """Per output -1/2 r^T K^-1 r - 1/2 log|K| - n/2 log 2 pi, summed, in float64."""
    x, r = np.asarray(x, np.float64), np.asarray(y, np.float64) - np.asarray(prior, np.float64)
    gram = _numpy_kernel(kernel, x, x) + kernel.noise * np.eye(len(x))
    _, log_det = np.linalg.slogdet(gram)
    quad = np.einsum("no,no->", r, np.linalg.solve(gram, r))
    return -0.5 * quad - 0.5 * r.shape[1] * (log_det + len(x) * math.log(2 * math.pi))


@pytest.mark.parametrize("kernel, dim, scale", [(RTE_KERNEL, 2, 0.1), (HTE_KERNEL, 9, 1.0)])
def test_log_marginal_likelihood_matches_float64_numpy(kernel, dim, scale):
    rng = np.random.default_rng(0)
    x = rng.uniform(0, scale, (10, dim)).astype(np.float32)
    prior = rng.normal(size=(10, 4)).astype(np.float32)
    y = (prior + 0.1 * rng.normal(size=(10, 4))).astype(np.float32)
    params = kernel_params(kernel)
    lml = jax.jit(log_marginal_likelihood, static_argnames="kind")
    # padded rows (capacity 16 > 10 observations) count for nothing
    got = float(lml(params, _fill(16, x, y, prior), kind=kernel.kind))
    want = _numpy_lml(kernel, x, y, prior)
    assert abs(got - want) <= 1e-4 * abs(want) + 1e-2
    # a full ring buffer (capacity 6) holds the last 6 observations
    got = float(lml(params, _fill(6, x, y, prior), kind=kernel.kind))
    want_ring = _numpy_lml(kernel, x[4:], y[4:], prior[4:])
    assert abs(got - want_ring) <= 1e-4 * abs(want_ring) + 1e-2
    assert abs(want_ring - want) > 1.0  # the forgotten rows matter (100 times the tolerance)
    # the prior is the mean: a constant shift of targets and prior together changes nothing
    shifted = float(lml(params, _fill(16, x, y + 1.0, prior + 1.0), kind=kernel.kind))
    assert abs(shifted - float(lml(params, _fill(16, x, y, prior), kind=kernel.kind))) < 1e-2
    # an empty buffer has likelihood 1
    assert float(lml(params, empty_gp(8, dim, 4), kind=kernel.kind)) == 0.0


def test_parameters_round_trip_and_the_noise_is_floored():
    kernel = Kernel("matern52", length_scale=0.3, variance=0.02, noise=0.0)
    back = kernel_of(kernel_params(kernel), kernel.kind)
    assert back.kind == "matern52"
    assert back.length_scale == pytest.approx(0.3, rel=1e-6) and back.variance == pytest.approx(0.02, rel=1e-6)
    assert back.noise == pytest.approx(1e-6, rel=1e-5)


def _sampled_datasets(length, variance, noise, count, points, seed):
    """`count` datasets of `points` 1-D inputs on [0, 1] with two outputs drawn from a squared
    exponential GP (float64), their priors drawn independently (the GP models target - prior)."""
    rng = np.random.default_rng(seed)
    truth = Kernel("squared_exponential", length, variance, noise)
    xs, ys, priors = [], [], []
    for _ in range(count):
        x = np.sort(rng.uniform(0, 1, (points, 1)), axis=0)
        gram = _numpy_kernel(truth, x, x) + noise * np.eye(points)
        residual = np.linalg.cholesky(gram) @ rng.normal(size=(points, 2))
        prior = rng.normal(size=(points, 2))
        xs.append(x), ys.append(prior + residual), priors.append(prior)
    return (np.asarray(v, np.float32) for v in (xs, ys, priors))


def test_fit_recovers_the_length_scale_of_a_known_gp():
    x, y, prior = _sampled_datasets(length=0.2, variance=1.0, noise=0.01, count=3, points=60, seed=0)
    capacity = 64  # 4 padded rows per dataset
    data = jax.tree.map(lambda *d: jnp.stack(d), *[_fill(capacity, *e) for e in zip(x, y, prior)])
    initial = Kernel("squared_exponential", length_scale=0.05, variance=0.3, noise=0.001)
    fitted, trace = fit_kernel(data, initial, steps=200, learning_rate=0.05)
    assert fitted.kind == initial.kind and isinstance(fitted.length_scale, float)
    assert fitted.length_scale == pytest.approx(0.2, rel=0.3)
    assert 0.4 < fitted.variance < 2.5 and fitted.noise == pytest.approx(0.01, rel=0.3)
    # and Adam reached the float64 maximum-likelihood kernel (Nelder-Mead on the NumPy formula)
    def negative(log_params):
        kernel = Kernel("squared_exponential", *map(float, np.exp(log_params)))
        return -sum(_numpy_lml(kernel, x[e], y[e], prior[e]) for e in range(3))

    best = np.exp(minimize(negative, np.log([0.05, 0.3, 0.001]), method="Nelder-Mead",
                           options={"xatol": 1e-6, "fatol": 1e-8, "maxiter": 4000}).x)
    np.testing.assert_allclose([fitted.length_scale, fitted.variance, fitted.noise], best, rtol=0.01)
    assert trace.shape == (201,) and np.isfinite(trace).all()
    assert trace[-1] > trace[0] + 100.0
    assert trace[-1] >= trace.max() - 1.0  # it ends at (about) the best it saw
    # the trace's ends are the likelihoods of the initial and the fitted kernel
    unpadded = [_numpy_lml(k, x[e], y[e], prior[e]) for k in (initial, fitted) for e in range(3)]
    assert trace[0] == pytest.approx(sum(unpadded[:3]), rel=1e-4, abs=0.05)
    assert trace[-1] == pytest.approx(sum(unpadded[3:]), rel=1e-4, abs=0.05)
