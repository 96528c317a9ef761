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
    """`run_together` calls each action's planning and acting (and waits for them) inside `warp_calls`."""
    from experiments.maze_eval import main as maze_main
    from hte_jax.online import episode

    monkeypatch.setattr(warp_calls, "_started", True)
    seen = []
    steps = episode.sharded_steps

    def recording_steps(*args, **kwargs):
        plan, plan_all, act, act_all = steps(*args, **kwargs)

        def recorded(fn):
            def call(*a):
                seen.append(gc.isenabled())
                return fn(*a)
            return call

        return recorded(plan), recorded(plan_all), recorded(act), recorded(act_all)

    monkeypatch.setattr(episode, "sharded_steps", recording_steps)
    args = ["--variant", "rte,2d-rte", "--damage", "none", "--replicates", "1", "--max-actions", "2", "--iterations",
            "8", "--roots", "1", "--out", str(tmp_path), "--no-progress"]
    assert maze_main(args) == 0
    assert len(seen) == 4 and not any(seen)  # 2 actions, each planning both batches together and acting them together
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


def _recorder():
    """(seen, record): record(x) appends whether the collector is on and returns x (a host callback's body)."""
    seen = []

    def record(x):
        seen.append(gc.isenabled())
        return x

    return seen, record


def test_modulation_re_executes_its_chunks_with_the_collector_paused(monkeypatch, collector_on, shipped_hbr):
    """`modulation.execute_held` (the modulation command's and the damage screen's re-executions, eager) waits for
    each chunk inside `warp_calls`: its summary, traced into the chunk's program, finds the collector off."""
    from hte_jax.hbr.composition import skill_ends
    from hte_jax.hbr.modulation import execute_held
    from hte_jax.sim.robot import load_robot
    from hte_jax.sim.rollout import standing_state

    monkeypatch.setattr(warp_calls, "_started", True)
    seen, record = _recorder()
    hbr, task = shipped_hbr
    slots = np.flatnonzero(np.asarray(hbr.top.filled))[:3]
    ends = np.asarray(skill_ends(hbr.top.descriptors[slots], hbr.top.extras["arrival_yaw"][slots], task.extent))
    robot = load_robot()
    start = standing_state(robot)

    def summarise(skill):
        xy = skill.displacement[:, :2]
        return (jax.pure_callback(record, jax.ShapeDtypeStruct(xy.shape, xy.dtype), xy),)

    (xy,) = execute_held(robot, hbr, start, np.asarray(hbr.top.genotypes)[slots], np.array([63, 0, 27]), ends, None,
                         summarise, chunk=2, progress=False)
    assert seen == [False, False] and gc.isenabled()  # two chunks (2 + 1 padded), each paused
    assert xy.shape == (3, 2) and np.all(np.isfinite(xy))


def test_damage_screen_runs_its_blocks_with_the_collector_paused(monkeypatch, collector_on):
    """benchmarks/damage_skills.py's `run_all` waits for each block inside `warp_calls`."""
    from tests.benchmark_runner import benchmark_module

    from hte_jax.sim.damage import make_damage, stack_damages

    monkeypatch.setattr(warp_calls, "_started", True)
    seen, record = _recorder()

    @jax.jit
    def fn(genotypes, damage, start):
        seen_genotypes = jax.pure_callback(record, jax.ShapeDtypeStruct(genotypes.shape, genotypes.dtype), genotypes)
        return (seen_genotypes + start[:, None],)

    damage = stack_damages([make_damage(np.eye(6, dtype=bool)[0], "raised"),
                            make_damage(np.eye(6, dtype=bool)[1], "removed")])
    start = np.array([0.0, 10.0])  # per condition
    (out,) = benchmark_module("damage_skills").run_all(fn, np.arange(6.0).reshape(3, 2), damage, start, chunk=4)
    assert len(seen) == 2 and not any(seen) and gc.isenabled()  # 6 (condition, skill) rows in 2 blocks of 3
    assert out.shape == (6, 2) and out[3, 0] == 10.0  # row c * K + k: condition 1, skill 0
