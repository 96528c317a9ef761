"""The stuck-leg check beside the tilt reflex (issue 36, 5c): while the reflex holds the neutral pose
the controller commands no gait, so the travel a leg is judged against is the travel of the targets
the robot commanded (`RolloutResult.target_travel`), not its elite's whole period; a healthy leg the
reflex held still is not stuck, a locked leg still is. Both robots the online loop drives: B robots
in MJX (`SimulatedRobots`) and one in native MuJoCo through its executor (`ExecutorRobot`). And
(5a) hte-spare's two detectors end to end in an episode batch: a raised leg flagged within two
actions, no leg of an intact robot."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.online.action import SimulatedRobots, learn_step
from hte_jax.online.external import ExecutorRobot, MujocoExecutor
from hte_jax.online.rules import SensedLegs, start_rules
from hte_jax.online.sensing import JOINT_EVIDENCE, stuck_legs
from hte_jax.online.skills import hbr_skills
from hte_jax.sim.controller import commanded_travel
from hte_jax.sim.damage import parse_damage
from hte_jax.sim.robot import NUM_LEGS, RobotConfig, load_robot
from hte_jax.sim.rollout import initial_state
from tests import xla_codegen

pytestmark = pytest.mark.slow

# The hte-jax protocol's reflex angle, holding (no release: the neutral pose to the end of the second,
# the worst case), on a robot whose damaged leg is locked in its standing pose.
REFLEX = dataclasses.replace(RobotConfig(), reflex_tilt=0.3, damage_model="locked")
DAMAGES = np.stack([np.zeros(NUM_LEGS, bool), parse_damage("leg1")])  # intact, leg 1 locked
TILT = math.radians(25.0)  # past the reflex angle: it fires at once


@pytest.fixture(scope="module")
def elite(shipped_hbr):
    """(HBR, its skills, the middle elite whose controller asks its least-moving leg the most)."""
    hbr, task = shipped_hbr
    filled = np.flatnonzero(np.asarray(hbr.middle.filled))
    least = np.asarray(commanded_travel(hbr.middle_params[filled])).min(axis=-1)
    assert least.max() > JOINT_EVIDENCE  # one second of it is evidence enough on every leg
    return hbr, hbr_skills(hbr, task, composition="waypoints"), int(filled[np.argmax(least)])


def _tilted(qpos: np.ndarray) -> np.ndarray:
    """qpos (..., 25) rolled by TILT about the body's x axis and lifted 5 cm."""
    qpos = np.array(qpos, np.float64)
    w, x, y, z = np.moveaxis(qpos[..., 3:7], -1, 0)
    c, s = math.cos(TILT / 2), math.sin(TILT / 2)  # q (x) (c, s, 0, 0)
    qpos[..., 3:7] = np.stack([w * c - x * s, x * c + w * s, y * c + z * s, z * c - y * s], axis=-1)
    qpos[..., 2] += 0.05
    return qpos


def _two_seconds(robots, skills, elite, state, batch):
    """Two seconds of `elite` from `state` (tilted), SensedLegs learning after each: the stuck legs
    (B, 6) after the first (held by the reflex) and after both, and after the first judged against
    the elite's whole period (what a robot that does not report its commands falls back to)."""
    rules = start_rules((SensedLegs(),), np.zeros(batch), np.zeros((batch, NUM_LEGS), bool), 2)
    elites, found, alive = jnp.full(batch, elite, jnp.int32), jnp.ones(batch, bool), jnp.ones(batch, bool)
    first = robots.second(state, skills.hbr, elites, found, alive)
    after_first, _ = learn_step(skills, rules, elites, first)
    second = robots.second(first.state, skills.hbr, elites, found, alive)
    after_both, _ = learn_step(skills, after_first, elites, second)
    assert np.asarray(first.valid).all() and np.asarray(second.valid).all()
    by_table = jnp.stack([first.leg_travel, commanded_travel(skills.hbr.middle_params[elites])], axis=1)
    return [np.asarray(stuck_legs(motion)) for motion in
            (after_first.states[0].motion, after_both.states[0].motion, by_table)]


def _check(first, both, by_table):
    assert not first.any()  # the reflex held every leg still: no gait was commanded
    assert both[0].tolist() == [False] * NUM_LEGS  # the intact robot walked its second second
    assert both[1].tolist() == [False, True, False, False, False, False]  # the locked leg did not
    assert by_table.all()  # judged against the elite's period, every leg the reflex held looks stuck


def test_mjx_robots_held_by_the_reflex_keep_their_healthy_legs_and_flag_a_locked_one(elite):
    _, skills, index = elite
    robot = load_robot(REFLEX)  # on an open floor
    start = jax.vmap(lambda damage: initial_state(robot, damage))(jnp.asarray(DAMAGES))
    start = start.replace(qpos=jnp.asarray(_tilted(start.qpos), jnp.float32))
    robots = SimulatedRobots(robot, jnp.asarray(DAMAGES))
    _check(*_two_seconds(robots, skills, index, start, 2))


def test_a_native_robot_held_by_the_reflex_keeps_its_healthy_legs_and_flags_a_locked_one(elite):
    _, skills, index = elite
    sensed = []
    for damage in DAMAGES:
        start = jax.tree.map(np.asarray, initial_state(load_robot(REFLEX), jnp.asarray(damage)))
        executor = MujocoExecutor(REFLEX, damage, start.replace(qpos=_tilted(start.qpos)))
        sensed.append(_two_seconds(ExecutorRobot(executor), skills, index, None, 1))
    _check(*(np.concatenate(rows) for rows in zip(*sensed)))


def test_the_leg_senses_flag_a_raised_leg_within_two_actions_and_no_leg_of_an_intact_robot(shipped_hbr):
    """hte-spare's detectors end to end, in MJX: after two actions the robot with leg 1 blocked in the
    air has sensed it off the floor and not following its joint commands, and nothing else; the
    intact robot flags no leg (its rule then still takes RTE's any pattern)."""
    from hte_jax.hbr.store import load_spare, spare_beside
    from hte_jax.online.evaluation import preset, run_batch, with_overrides
    from hte_jax.online.sensing import stuck_legs, unusable_legs

    with xla_codegen.at_defaults():  # the shipped spare archive's lookup (kept for run_batch's load): ~5 CPU s, ~19 fast
        load_spare(spare_beside(None), shipped_hbr[0])
    config = with_overrides(preset("cpu"), {"variants": "hte-spare", "damages": "none,leg1", "max_actions": "2",
                                            "iterations": "50", "roots": "1"})
    result = run_batch(config, None, ["hte-spare"], progress=False)
    episodes = result.episodes
    assert int(episodes.taken.min()) == 2 and not bool(episodes.broken.any())
    sense = episodes.rules.states[0]
    off_floor = np.asarray(unusable_legs(sense.contacts))
    stuck = np.asarray(stuck_legs(sense.motion))
    assert result.damages == ["none", "leg1"]
    assert not off_floor[0].any() and not stuck[0].any()
    assert off_floor[1].tolist() == [False, True, False, False, False, False]
    assert stuck[1].tolist() == [False, True, False, False, False, False]
    patterns = np.asarray(episodes.history.patterns)
    assert (patterns[0, :2] == -1).all()  # intact: RTE's choice throughout
    assert patterns[1, 1, -1] == 0b101111  # leg 1 lifted by the last step of the second action
