"""The garbage collector paused while device work that may run Warp's calls is in flight (`hte_jax.warp_calls`):
a host callback inside a MAP-Elites generation, as Warp's FFI runs one per physics step, sees no collector; and
before Warp starts nothing changes."""

import gc

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax import warp_calls
from hte_jax.qd import Grid, MapElites, MapElitesConfig, run
from hte_jax.qd.loop import start_or_resume
from hte_jax.qd.tasks import planar_arm_evaluate


@pytest.fixture
def collector_on():
    """The collector enabled for the test and restored after it."""
    was = gc.isenabled()
    gc.enable()
    yield
    (gc.enable if was else gc.disable)()


def test_collection_is_paused_inside_once_warp_started_and_resumes_after(monkeypatch, collector_on):
    monkeypatch.setattr(warp_calls, "_started", False)
    with warp_calls.warp_calls():
        assert gc.isenabled()  # Warp not started: nothing changes
    monkeypatch.setattr(warp_calls, "_started", True)
    with warp_calls.warp_calls():
        assert not gc.isenabled()
    assert gc.isenabled()
    with pytest.raises(RuntimeError, match="inside"):
        with warp_calls.warp_calls():
            raise RuntimeError("inside")
    assert gc.isenabled()  # restored when the work inside fails
    gc.disable()
    with warp_calls.warp_calls():
        pass
    assert not gc.isenabled()  # a collector the caller turned off stays off


def test_a_host_callback_inside_a_generation_runs_with_the_collector_paused(monkeypatch, collector_on):
    """The QD loop's blocks and initial batch wait for their device work inside `warp_calls`: a Python callback
    in the evaluation (Warp's FFI runs one per physics step) finds the collector off, and on again after."""
    monkeypatch.setattr(warp_calls, "_started", True)
    seen = []

    def record(x):
        seen.append(gc.isenabled())
        return x

    def evaluate(key, genotypes):
        genotypes = jax.pure_callback(record, jax.ShapeDtypeStruct(genotypes.shape, genotypes.dtype), genotypes)
        return planar_arm_evaluate(key, genotypes)

    config = MapElitesConfig(batch_size=16, init_size=16, mutation_rate=0.2, qd_offset=-np.pi)
    algo = MapElites(Grid(bins=(8, 8), low=(0.0, 0.0), high=(1.0, 1.0)), evaluate, 4, config)
    state = start_or_resume(algo, jax.random.PRNGKey(0), "/nonexistent/checkpoint.npz", progress=False)
    state = run(algo, state, 4, block_size=2, progress=False)
    assert int(state.generation) == 4
    assert len(seen) >= 5 and not any(seen)  # the initial batch and 4 generations' evaluations
    assert gc.isenabled()
    assert int(jnp.sum(state.repertoire.filled)) > 0


def test_maze_eval_plans_and_acts_with_the_collector_paused(monkeypatch, tmp_path, collector_on):
    """`run_episodes` calls each action's planning and acting (and waits for them) inside `warp_calls`."""
    from experiments.maze_eval import main as maze_main
    from hte_jax.online import episode

    monkeypatch.setattr(warp_calls, "_started", True)
    seen = []
    steps = episode.sharded_steps

    def recording_steps(*args, **kwargs):
        plan, act = steps(*args, **kwargs)

        def recorded(fn):
            def call(*a):
                seen.append(gc.isenabled())
                return fn(*a)
            return call

        return recorded(plan), recorded(act)

    monkeypatch.setattr(episode, "sharded_steps", recording_steps)
    args = ["--variant", "rte", "--damage", "none", "--replicates", "1", "--max-actions", "2", "--iterations", "8",
            "--roots", "1", "--out", str(tmp_path), "--no-progress"]
    assert maze_main(args) == 0
    assert len(seen) == 4 and not any(seen)  # 2 actions, each planned and acted
    assert gc.isenabled()


def test_waited_returns_the_finished_result_with_the_collector_paused_during_the_call(monkeypatch, collector_on):
    monkeypatch.setattr(warp_calls, "_started", True)
    seen = []

    def record(x):
        seen.append(gc.isenabled())
        return x

    @jax.jit
    def work(x, scale):
        return jax.pure_callback(record, jax.ShapeDtypeStruct(x.shape, x.dtype), x) * scale

    out = warp_calls.waited(work, jnp.arange(4.0), scale=2.0)
    assert seen == [False] and gc.isenabled()  # paused while the device work ran, on again after
    assert out.is_ready() and np.array_equal(np.asarray(out), [0.0, 2.0, 4.0, 6.0])


def test_standing_state_settles_with_the_collector_paused_and_under_a_callers_jit_as_before(monkeypatch, collector_on):
    """Every command's start (`standing_state`, eager) waits for its rollout inside `warp_calls`; traced under a
    caller's jit it leaves the waiting to that caller."""
    import importlib

    from hte_jax.sim.robot import load_robot

    rollout_module = importlib.import_module("hte_jax.sim.rollout")  # the module (the package exports its function)

    monkeypatch.setattr(warp_calls, "_started", True)
    seen = []
    real = rollout_module.rollout

    def record(x):
        seen.append(gc.isenabled())
        return x

    def recorded_rollout(robot, params, damage, init, spec):
        params = jax.pure_callback(record, jax.ShapeDtypeStruct(params.shape, params.dtype), jnp.asarray(params))
        return real(robot, params, damage, init, spec)

    monkeypatch.setattr(rollout_module, "rollout", jax.jit(recorded_rollout, static_argnames=("spec",)))
    robot = load_robot()
    eager = rollout_module.standing_state(robot, np.eye(6, dtype=bool)[:2], settle_steps=4)
    assert seen == [False] and gc.isenabled()
    assert eager.qpos.shape[0] == 2 and np.all(np.isfinite(np.asarray(eager.qpos)))
    traced = jax.jit(lambda d: rollout_module.standing_state(robot, d, settle_steps=4))(jnp.eye(6, dtype=bool)[:2])
    assert np.allclose(np.asarray(traced.qpos), np.asarray(eager.qpos), atol=1e-6)
