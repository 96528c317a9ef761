"""The online GPs: posterior against a float64 NumPy reference, masked = unpadded, no retracing."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.online.gp import HTE_KERNEL, RTE_KERNEL, Kernel, add_observation, empty_gp, posterior


def _numpy_kernel(kernel, a, b):
    r2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1) / kernel.length_scale**2
    if kernel.kind == "squared_exponential":
        return kernel.variance * np.exp(-0.5 * r2)
    r = np.sqrt(r2)
    return kernel.variance * (1 + np.sqrt(5) * r + 5 * r2 / 3) * np.exp(-np.sqrt(5) * r)


def _numpy_posterior(kernel, x, y, prior_x, q, prior_q):
    """Textbook GP regression in float64."""
    x, y, q = (np.asarray(v, np.float64) for v in (x, y, q))
    gram = _numpy_kernel(kernel, x, x) + kernel.noise * np.eye(len(x))
    cross = _numpy_kernel(kernel, q, x)
    mean = prior_q + cross @ np.linalg.solve(gram, y - prior_x)
    variance = kernel.variance - np.einsum("qn,nq->q", cross, np.linalg.solve(gram, cross.T))
    return mean, variance


def _fill(capacity, x, y, prior=None):
    data = empty_gp(capacity, x.shape[1], y.shape[1])
    for i in range(len(x)):
        data = add_observation(data, jnp.asarray(x[i]), jnp.asarray(y[i]), None if prior is None else jnp.asarray(prior[i]))
    return data


@pytest.mark.parametrize("kernel, dim, scale", [(RTE_KERNEL, 2, 0.05), (HTE_KERNEL, 9, 1.0)])
def test_posterior_matches_float64_numpy(kernel, dim, scale):
    rng = np.random.default_rng(0)
    x = rng.uniform(0, scale, (9, dim)).astype(np.float32)
    y = rng.normal(size=(9, 4)).astype(np.float32)
    prior_x = rng.normal(size=(9, 4)).astype(np.float32)
    q = np.concatenate([x[:3], rng.uniform(0, scale, (20, dim))]).astype(np.float32)
    prior_q = rng.normal(size=(23, 4)).astype(np.float32)
    data = _fill(16, x, y, prior_x)
    mean, variance = posterior(kernel, data, jnp.asarray(q), jnp.asarray(prior_q))
    want_mean, want_var = _numpy_posterior(kernel, x, y, prior_x, q, prior_q)
    np.testing.assert_allclose(np.asarray(mean), want_mean, atol=2e-4, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(variance), np.maximum(want_var, 0), atol=2e-6 * kernel.variance / 0.01)
    # data-mean prior (limbo mean::Data): the constant is the mean of the observed targets
    mean, variance = posterior(kernel, data, jnp.asarray(q))
    constant = y.astype(np.float64).mean(axis=0)
    want_mean, _ = _numpy_posterior(kernel, x, y, np.broadcast_to(constant, y.shape), q, np.broadcast_to(constant, (23, 4)))
    np.testing.assert_allclose(np.asarray(mean), want_mean, atol=2e-4, rtol=1e-4)


def test_masked_buffer_equals_the_unpadded_gp_and_forgets_the_oldest():
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 0.1, (6, 2)).astype(np.float32)
    y = rng.normal(size=(6, 4)).astype(np.float32)
    q = jnp.asarray(rng.uniform(0, 0.1, (11, 2)), jnp.float32)
    prior_q = jnp.zeros((11, 4))
    exact = posterior(RTE_KERNEL, _fill(6, x, y), q, prior_q)
    padded = posterior(RTE_KERNEL, _fill(64, x, y), q, prior_q)
    for got, want in zip(padded, exact):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-6)
    # A full ring buffer keeps the last 4 observations, in another slot order than a fresh GP of
    # them: float32 rounding then differs by a few 1e-6 and by how much depends on the CPU's
    # kernels, so both are held to the float64 posterior of those 4, within the float32 tolerance
    # of test_posterior_matches_float64_numpy.
    ring_mean, ring_var = posterior(RTE_KERNEL, _fill(4, x, y), q, prior_q)
    want_mean, want_var = _numpy_posterior(RTE_KERNEL, x[2:], y[2:], np.zeros((4, 4)), q, np.zeros((11, 4)))
    np.testing.assert_allclose(np.asarray(ring_mean), want_mean, atol=2e-4, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(ring_var), np.maximum(want_var, 0), atol=2e-6)
    assert np.abs(np.asarray(exact[0]) - want_mean).max() > 100 * 2e-4  # forgetting the oldest two matters
    last_mean, _ = posterior(RTE_KERNEL, _fill(4, x[2:], y[2:]), q, prior_q)
    np.testing.assert_allclose(np.asarray(ring_mean), np.asarray(last_mean), atol=2e-4, rtol=1e-4)
    empty_mean, empty_var = posterior(RTE_KERNEL, empty_gp(8, 2, 4), q, prior_q + 3.0)
    np.testing.assert_allclose(np.asarray(empty_mean), 3.0)
    np.testing.assert_allclose(np.asarray(empty_var), RTE_KERNEL.variance)


def test_adding_points_never_retraces():
    traces = {"add": 0, "posterior": 0}

    @jax.jit
    def add(data, x, y):
        traces["add"] += 1
        return add_observation(data, x, y)

    @jax.jit
    def predict(data, q):
        traces["posterior"] += 1
        return posterior(HTE_KERNEL, data, q)

    data = empty_gp(32, 9, 3)
    q = jnp.linspace(0, 1, 90).reshape(10, 9)
    for i in range(20):
        data = add(data, jnp.full((9,), i / 20.0), jnp.full((3,), float(i)))
        predict(data, q)
    assert traces == {"add": 1, "posterior": 1}
    assert int(data.count) == 20 and int(data.mask.sum()) == 20


def test_kernel_settings_are_checked():
    with pytest.raises(ConfigError, match="kernel kind"):
        Kernel("rbf", 1.0, 1.0, 0.0)
    with pytest.raises(ConfigError, match="length_scale"):
        Kernel("matern52", 0.0, 1.0, 0.0)
    with pytest.raises(ConfigError, match="GP capacity"):
        empty_gp(0, 2, 2)


def _lapack_calls(compiled_text: str) -> list[tuple[str, str]]:
    """(target, result shape) of every LAPACK custom call in a compiled CPU program."""
    calls = []
    for line in compiled_text.splitlines():
        target = re.search(r'custom_call_target="(lapack_[a-z]+_ffi)"', line)
        if target:
            calls.append((target.group(1), line.split("=", 1)[1].split("custom-call")[0].strip()))
    return calls


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="checks the CPU program")
def test_batched_posteriors_factor_one_matrix_per_lapack_call_on_the_cpu():
    """jaxlib's CPU LAPACK kernels split a batched call over the intra-op thread pool and wait for
    it; two at once hung `maze_eval` on a 2-core machine. Batched GPs (episodes x repertoires, as
    the planner's) must reach LAPACK one matrix at a time, and give the batched call's bits."""
    rng = np.random.default_rng(1)
    episodes, maps, capacity = 3, 2, 12
    x = rng.uniform(0, 0.05, (episodes, maps, capacity, 2)).astype(np.float32)
    y = rng.normal(0, 0.01, (episodes, maps, capacity, 4)).astype(np.float32)
    data = jax.vmap(jax.vmap(lambda x, y: _fill(capacity, x[:7], y[:7])))(jnp.asarray(x), jnp.asarray(y))
    queries = jnp.asarray(rng.uniform(0, 0.05, (5, 2)).astype(np.float32))

    def batched(data):
        return jax.vmap(jax.vmap(lambda d: posterior(RTE_KERNEL, d, queries, jnp.zeros((5, 4)))))(data)

    calls = _lapack_calls(jax.jit(batched).lower(data).compile().as_text())
    assert {target for target, _ in calls} == {"lapack_spotrf_ffi", "lapack_strsm_ffi"}
    for target, shape in calls:
        dims = re.search(r"f32\[([\d,]+)\]", shape).group(1).split(",")
        assert len(dims) == 2, f"{target} runs a batch {shape}"
    mean, variance = jax.jit(batched)(data)
    for e in range(episodes):
        for k in range(maps):
            one = jax.tree.map(lambda a: a[e, k], data)
            m, v = posterior(RTE_KERNEL, one, queries, jnp.zeros((5, 4)))
            np.testing.assert_allclose(mean[e, k], m, rtol=0, atol=1e-6)
            np.testing.assert_allclose(variance[e, k], v, rtol=0, atol=1e-7)
