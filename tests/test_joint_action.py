"""Batches planned and acted together (`episode.plan_steps`; `action.joint_action` through `episode.act_steps`):
each batch's decisions are those of its own `plan_step`, and its episodes after the joint action those of its own
`act_step`, up to float rounding (a rollout of more rows rounds differently),
robots that start invalid included; `maze_eval --together` runs a seed's batches either way, and under
`--spread batches` a seed's batches go to one worker, which runs them together (2 forced CPU devices; the default
`--together seed` on 2 devices, episodes split over them, runs in `test_commands`)."""

import json
import subprocess
import sys
from operator import attrgetter

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.maze_eval import main as maze_main
from hte_jax.online.arena import maze_robot
from hte_jax.online.episode import act_step, act_steps, plan_step, plan_steps, start_episodes
from hte_jax.online.evaluation import batch_labels, batches, load_skills, preset, with_overrides
from hte_jax.online.arena import start_states
from hte_jax.online.maze import distance_field
from hte_jax.online.variants import batch_rules
from hte_jax.qd.io import read_checkpoint
from hte_jax.sim.damage import mask_if_plain, stack_damages
from tests.benchmark_runner import benchmark_module
from tests.processes import ROOT, cpu_devices_env

pytestmark = pytest.mark.slow

CONFIG = with_overrides(preset("cpu"), {"variants": "hte-spare,2d-rte", "damages": "none,leg1,legs1+4", "replicates": 1,
                                         "reflex_tilt": 0.3, "reflex_release": 0.15,
                                         "iterations": 8, "roots": 1})


def _flipped(state, row):
    """`state` with robot `row` upside down (invalid before its first step)."""
    return state.replace(qpos=state.qpos.at[row, 3:7].set(jnp.asarray([0.0, 1.0, 0.0, 0.0])))


def _batch(config, path, variants, key):
    skills, _ = load_skills(path, spare=any(v == "hte-spare" for v in variants))
    labels = batch_labels(config, variants)
    rules, which = batch_rules([v for v, _, _ in labels])
    damage = mask_if_plain(stack_damages([config.damage_conditions[d] for _, d, _ in labels]), config.damage_model)
    start = start_states(config.maze_task, damage, config.robot)
    episodes = start_episodes(config.adaptation, skills, start, damage, rules, np.asarray(which), key)
    return skills, episodes.replace(sim=_flipped(episodes.sim, 1))


def test_batches_acted_together_match_each_batch_acted_alone():
    maze, adaptation = CONFIG.maze_task, CONFIG.adaptation
    robot = maze_robot(maze, CONFIG.robot)
    field = distance_field(maze, adaptation.grid)
    parts = [_batch(CONFIG, path, variants, jax.random.PRNGKey(k))
             for k, (_, path, variants) in enumerate(batches(CONFIG))]
    assert [s.hierarchical for s, _ in parts] == [True, False]
    decisions = [plan_step(maze, adaptation, s, field, e) for s, e in parts]
    # planned together: one search of both batches, the smaller action set padded with unusable actions
    assert parts[0][0].actions.size != parts[1][0].actions.size
    joint = plan_steps(maze, adaptation, tuple(s for s, _ in parts), field, tuple(e for _, e in parts))
    for one, both in zip(decisions, joint):
        for name in ("map", "action", "plan.action", "plan.visits", "plan.path_length"):
            np.testing.assert_array_equal(attrgetter(name)(one), attrgetter(name)(both), err_msg=name)
        for name in ("plan.value", "plan.path", "predicted", "prior", "start"):
            np.testing.assert_allclose(attrgetter(name)(one), attrgetter(name)(both), atol=1e-5, err_msg=name)
        np.testing.assert_array_equal(one.keys, both.keys)
    alone = [act_step(maze, adaptation, robot, s, e, d)[0] for (s, e), d in zip(parts, decisions)]
    together, states = act_steps(maze, adaptation, robot, tuple(s for s, _ in parts), tuple(e for _, e in parts),
                                 tuple(decisions))
    assert states == (None, None)
    for one, joint in zip(alone, together):
        assert one.broken.tolist() == joint.broken.tolist() == [False, True, False]  # the flipped robot ends
        np.testing.assert_array_equal(one.reason, joint.reason)
        np.testing.assert_array_equal(one.taken, joint.taken)
        np.testing.assert_array_equal(one.history.patterns, joint.history.patterns)
        np.testing.assert_array_equal(one.history.action, joint.history.action)
        # float rounding, not a different action: millimetres after 4 s of contact-rich walking
        np.testing.assert_allclose(one.trajectory, joint.trajectory, atol=2e-3)
        np.testing.assert_allclose(one.sim.qpos, joint.sim.qpos, atol=5e-3)
        np.testing.assert_allclose(one.history.observed, joint.history.observed, atol=2e-3)
        np.testing.assert_allclose(one.history.contacts, joint.history.contacts, atol=0.05)
    moved = np.linalg.norm(np.asarray(alone[1].history.observed[:, 0, :2]), axis=-1)
    assert moved[0] > 0.05 and moved[1] == 0.0  # the flat skill walked; the flipped robot stayed where it stopped


def test_maze_eval_runs_a_seeds_batches_together_or_one_at_a_time(tmp_path, capsys):
    args = ["--variant", "rte,2d-rte", "--damage", "leg1", "--replicates", "1", "--max-actions", "2", "--iterations",
            "8", "--roots", "1", "--no-progress"]
    runs = {}
    for which in ("seed", "none"):
        assert maze_main([*args, "--together", which, "--out", str(tmp_path / which)]) == 0
        runs[which] = json.loads((tmp_path / which / "episodes.json").read_text())["episodes"]
    assert [(r["variant"], r["actions_taken"]) for r in runs["seed"]] == [("rte", 2), ("2d-rte", 2)]
    for a, b in zip(runs["seed"], runs["none"]):
        assert (a["variant"], a["actions_taken"], a["reached"]) == (b["variant"], b["actions_taken"], b["reached"])
        np.testing.assert_allclose(a["prediction_error"], b["prediction_error"], atol=5e-3)
    # the batch files name the batches run together; protocol_time counts their shared acting once
    read_run = benchmark_module("protocol_time").read_run
    for which, groups in (("seed", [[0, 1], [0, 1]]), ("none", [[0], [1]])):
        run, _ = read_run(tmp_path / which)
        assert [b["run_with"] for b in run["batches"]] == groups
        labels = [read_checkpoint(tmp_path / which / f"episodes_{k}.npz")[1]["metadata"] for k in (0, 1)]
        # together, batch 1's planning, acting and setup are batch 0's
        same = [labels[0][name] == labels[1][name] for name in ("plan_seconds", "act_seconds", "setup_seconds")]
        assert same == [which == "seed"] * 3
        assert [b["plan_shared"] for b in run["batches"]] == [which == "seed"] * 2
        assert run["batches_s"] == pytest.approx(sum(b["seconds"] for b in run["batches"])
                                                 - run["batches"][1]["seconds"] * (which == "seed"))
    capsys.readouterr()
    assert maze_main([*args, "--together", "all", "--out", str(tmp_path / "bad")]) == 2
    assert capsys.readouterr().err.strip() == "error: --together must be one of seed, none, got 'all'"


def test_spread_batches_gives_a_seeds_batches_to_one_worker_that_runs_them_together(tmp_path):
    args = ["--variant", "rte,2d-rte", "--damage", "leg1", "--replicates", "1", "--max-actions", "2", "--iterations",
            "8", "--roots", "1", "--no-progress"]
    spread = subprocess.run([sys.executable, "-m", "experiments.maze_eval", *args, "--devices", "2", "--spread",
                             "batches", "--out", str(tmp_path / "spread")], cwd=ROOT, env=cpu_devices_env(2),
                            capture_output=True, text=True, timeout=600)
    assert spread.returncode == 0, spread.stderr[-3000:]
    lines = [line for line in spread.stdout.splitlines() if line.startswith("batch ")]
    assert [line.split(":")[0] for line in lines] == ["batch 0 (rte on seed 0", "batch 1 (2d-rte on seed 0"]
    # one worker ran both, together: the same arrays as a one-device run of both together, bit for bit
    assert maze_main([*args, "--devices", "1", "--out", str(tmp_path / "one")]) == 0
    for k in (0, 1):
        ours, theirs = (read_checkpoint(tmp_path / run / f"episodes_{k}.npz")[0] for run in ("spread", "one"))
        assert ours.keys() == theirs.keys() and all(np.array_equal(ours[name], theirs[name]) for name in ours)
