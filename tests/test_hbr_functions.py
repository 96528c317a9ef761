"""Pure pieces of the HBR: geometry, angle error, descriptors, lookups, genotype decoding (acceptance 1),
and the leg primitives measured in MJX on hand-made genes."""

import math
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.sim.robot import FOOT_REACH
from hte_jax.hbr.bottom import (
    BottomTask,
    activation_fitness,
    duty_level,
    evaluate_bottom,
    gene_fitness,
    leg_params,
    lift_height,
    swing_distance,
)
from hte_jax.hbr.analysis import fitness_by_distance, speed_by_turn
from hte_jax.hbr.hierarchy import HBR, select_middle, skill_waypoints
from hte_jax.geometry import angle_error, compose_pose, heading, medoid_index, planar_pose, relative_pose, wrap_angle
from hte_jax.hbr.middle import MiddleTask, decode, elite_controllers, leg_controllers, nearest_index, pattern_bits, pattern_code
from hte_jax.hbr.top import TopTask
from hte_jax.qd.repertoire import Repertoire, empty_repertoire
from hte_jax.sim.rollout import standing_state


def _yaw_quat(yaw):
    return np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], axis=-1)


def test_arc_motion_has_known_angle_error():
    # A robot carried along a left arc of radius 0.4 m through phi, its heading tangent to the arc,
    # starting at (0.3, -0.2) facing 0.7 rad: measured through quaternions and the start frame.
    radius, phis = 0.4, np.array([0.2, 0.9, 2.0, -1.1])
    start = np.array([0.3, -0.2, 0.7])
    local = np.stack([radius * np.sin(np.abs(phis)), radius * (1 - np.cos(phis)) * np.sign(phis), phis], -1)
    end = np.asarray(compose_pose(jnp.asarray(np.broadcast_to(start, local.shape)), jnp.asarray(local)))
    pos = np.concatenate([end[:, :2], np.full((4, 1), 0.13)], -1)
    start_pose = planar_pose(jnp.asarray([[*start[:2], 0.13]] * 4), jnp.asarray(_yaw_quat(np.full(4, start[2]))))
    end_pose = planar_pose(jnp.asarray(pos), jnp.asarray(_yaw_quat(end[:, 2])))
    motion = relative_pose(start_pose, end_pose)
    np.testing.assert_allclose(np.asarray(motion), local, atol=1e-5)
    np.testing.assert_allclose(np.asarray(angle_error(motion)), 0.0, atol=1e-5)
    # Arriving 0.3 rad off the tangent costs exactly 0.3.
    off = motion.at[:, 2].add(0.3)
    np.testing.assert_allclose(np.asarray(angle_error(off)), -0.3, atol=1e-5)


@pytest.mark.parametrize(
    "motion, expected",
    [((0.3, 0.0, 0.0), 0.0), ((-0.3, 0.0, 0.0), 0.0), ((0.0, 0.3, 0.0), -math.pi), ((0.0, 0.3, math.pi), 0.0),
     ((0.2, 0.2, 0.0), -math.pi / 2), ((0.2, 0.2, math.pi / 2), 0.0), ((0.2, -0.2, -math.pi / 2), 0.0)],
)
def test_angle_error_hand_cases(motion, expected):
    assert float(angle_error(jnp.asarray(motion))) == pytest.approx(expected, abs=1e-5)


def test_heading_ignores_tilt_and_poses_invert():
    # Yaw 0.8 then a 0.3 rad roll: heading is still 0.8.
    yaw, roll = 0.8, 0.3
    qz = np.array([math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)])
    qx = np.array([math.cos(roll / 2), math.sin(roll / 2), 0, 0])
    w1, x1, y1, z1 = qz
    w2, x2, y2, z2 = qx
    q = np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                  w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])
    assert float(heading(jnp.asarray(q))) == pytest.approx(yaw, abs=1e-6)
    rng = np.random.default_rng(0)
    a = jnp.asarray(rng.uniform(-2, 2, (50, 3)))
    b = jnp.asarray(rng.uniform(-2, 2, (50, 3)))
    back = compose_pose(a, relative_pose(a, b))
    np.testing.assert_allclose(np.asarray(back[:, :2]), np.asarray(b[:, :2]), atol=1e-5)
    np.testing.assert_allclose(np.asarray(wrap_angle(back[:, 2] - b[:, 2])), 0.0, atol=1e-5)


def test_medoid_matches_numpy():
    rng = np.random.default_rng(1)
    points = rng.normal(size=(20, 7, 3)).astype(np.float32)
    points[3, 5] = 100.0  # an outlier never becomes the medoid
    expected = [np.argmin(np.linalg.norm(p[:, None] - p[None], axis=-1).sum(-1)) for p in points]
    np.testing.assert_array_equal(np.asarray(medoid_index(jnp.asarray(points))), expected)


def test_swing_and_height_hand_cases():
    steps = 100
    hip = np.zeros(steps, np.float32)
    hip[20:60] = -np.linspace(0, 0.2, 40)  # falls 0.2 rad ...
    hip[60:] = hip[59]
    contact = np.zeros(steps, bool)
    contact[10:70] = True  # ... all of it with the foot down
    assert float(swing_distance(jnp.asarray(hip), jnp.asarray(contact))) == pytest.approx(FOOT_REACH * 0.2, rel=1e-5)
    assert float(swing_distance(jnp.asarray(hip), jnp.zeros(steps, bool))) == 0.0  # foot in the air: no stroke
    assert float(swing_distance(jnp.asarray(-hip), jnp.asarray(contact))) == pytest.approx(-FOOT_REACH * 0.2, rel=1e-5)
    base = 0.13 + 0.002 * np.sin(np.arange(steps) / 7.0)
    foot = np.full(steps, 0.025) + 0.0
    # The foot stays on the floor while the body bobs: height is the body's motion, opposite sign.
    h = float(lift_height(jnp.asarray(foot), jnp.asarray(base)))
    assert abs(h) <= 0.004 + 1e-6
    lifted = foot.copy()
    lifted[30:50] += 0.03 * np.sin(np.linspace(0, np.pi, 20))
    assert float(lift_height(jnp.asarray(lifted), jnp.full(steps, 0.13))) == pytest.approx(0.03 * np.sin(np.pi * 9 / 19), rel=1e-4)
    pushed = foot.copy()
    assert float(lift_height(jnp.asarray(pushed), jnp.asarray(0.13 + np.linspace(0, 0.02, steps)))) == pytest.approx(-0.02, rel=1e-5)


def test_duty_levels_and_activation():
    duty = jnp.asarray([0.0, 0.1, 0.2499, 0.25, 0.5, 0.74, 0.75, 0.99, 1.0])
    np.testing.assert_allclose(np.asarray(duty_level(duty)), [0, 0, 0, 1 / 3, 2 / 3, 2 / 3, 1, 1, 1], atol=1e-6)
    # A leg commanded at the full 5 rad/s on all joints for 1 s scores -1; a still leg 0.
    assert float(activation_fitness(jnp.full(3, 5.0), 1.0, 5.0)) == pytest.approx(-1.0)
    assert float(activation_fitness(jnp.zeros(3), 1.0, 5.0)) == 0.0


def test_original_gene_fitness_option():
    """The original's bottom fitness: minus the sum of all six genes (phases and duties too) over 3."""
    genes = jnp.asarray([[0.0] * 6, [1.0] * 6, [0.5, 0.2, 0.0, 0.1, 0.9, 0.3]], jnp.float32)
    np.testing.assert_allclose(np.asarray(gene_fitness(genes)), [0.0, -2.0, -2.0 / 3], rtol=1e-6)
    assert BottomTask(fitness="genes").fitness == "genes"
    with pytest.raises(ConfigError, match="bottom fitness must be one of"):
        BottomTask(fitness="energy")


def test_leg_params_drive_only_the_chosen_leg():
    genes = jnp.asarray(np.random.default_rng(2).uniform(size=(4, 6)), jnp.float32)
    params = np.asarray(leg_params(genes, jnp.asarray([0, 3, 5, 2])))
    for row, leg in enumerate([0, 3, 5, 2]):
        np.testing.assert_array_equal(params[row].reshape(6, 6)[leg], np.asarray(genes[row]))
        assert np.count_nonzero(np.delete(params[row].reshape(6, 6), leg, axis=0)) == 0


def test_nearest_primitive_lookup_matches_numpy():
    rng = np.random.default_rng(3)
    capacity = 300
    points = rng.uniform(size=(capacity, 3)).astype(np.float32)
    points[7] = points[3]  # duplicate: ties go to the lower slot
    mask = rng.uniform(size=capacity) < 0.7
    mask[3] = mask[7] = True
    queries = rng.uniform(size=(5, 6, 3)).astype(np.float32)
    queries[0, 0] = points[3]
    dist = ((queries[..., None, :] - points) ** 2).sum(-1)
    expected = np.argmin(np.where(mask, dist, np.inf), axis=-1)
    got = np.asarray(nearest_index(jnp.asarray(points), jnp.asarray(mask), jnp.asarray(queries), chunk=7))
    np.testing.assert_array_equal(got, expected)
    assert got[0, 0] == 3
    assert int(nearest_index(jnp.asarray(points), jnp.zeros(capacity, bool), jnp.asarray(queries[0, 0]))) == -1
    genes = rng.uniform(size=(capacity, 6)).astype(np.float32)
    bottom = Repertoire(genotypes=jnp.asarray(genes), descriptors=jnp.asarray(points),
                        fitnesses=jnp.zeros(capacity), filled=jnp.asarray(mask))
    params = np.asarray(leg_controllers(bottom, jnp.asarray(queries)))
    np.testing.assert_array_equal(params, genes[expected].reshape(5, 36))


def test_elite_controllers_equal_the_masked_lookup_of_every_row():
    """The host-side lookup of filled rows among filled bottom elites gives, bit for bit, what the
    whole-capacity lookup (the jitted path) gives; ties, empty rows and an empty bottom included."""
    import jax

    rng = np.random.default_rng(5)
    cells, capacity = 400, 90
    points = rng.uniform(size=(cells, 3)).astype(np.float32)
    points[11] = points[4]  # duplicate filled descriptors: ties go to the lower slot
    bottom_filled = rng.uniform(size=cells) < 0.6
    bottom_filled[[4, 11]] = True
    bottom_filled[:3] = False  # empty cells before the first filled one
    bottom = Repertoire(genotypes=jnp.asarray(rng.uniform(size=(cells, 6)).astype(np.float32)),
                        descriptors=jnp.asarray(points), fitnesses=jnp.zeros(cells), filled=jnp.asarray(bottom_filled))
    genotypes = rng.uniform(size=(capacity, 18)).astype(np.float32)
    genotypes[5, :3] = points[4]  # a leg target exactly on the duplicated descriptor
    genotypes[6, :3] = points[0]  # ... and exactly on an empty cell's descriptor
    filled = rng.uniform(size=capacity) < 0.4
    filled[[5, 6]] = True

    def masked(bottom, genotypes, filled):
        return jnp.where(filled[:, None], leg_controllers(bottom, decode(genotypes)), 0.0)

    expected = np.asarray(masked(bottom, jnp.asarray(genotypes), jnp.asarray(filled)))
    got = np.asarray(elite_controllers(bottom, jnp.asarray(genotypes), jnp.asarray(filled)))
    assert got.dtype == expected.dtype and got.shape == (capacity, 36)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(got[5, :6], np.asarray(bottom.genotypes)[4])
    assert (got[~filled] == 0).all() and (got[filled] != 0).any()
    traced = jax.jit(elite_controllers)(bottom, jnp.asarray(genotypes), jnp.asarray(filled))  # the jitted path
    np.testing.assert_array_equal(np.asarray(traced), expected)
    nothing = elite_controllers(bottom, jnp.asarray(genotypes), jnp.zeros(capacity, bool))
    assert (np.asarray(nothing) == 0).all()
    empty = bottom.replace(filled=jnp.zeros(cells, bool))
    np.testing.assert_array_equal(np.asarray(elite_controllers(empty, jnp.asarray(genotypes), jnp.asarray(filled))),
                                  np.asarray(masked(empty, jnp.asarray(genotypes), jnp.asarray(filled))))


def test_elite_controllers_keep_their_last_results_by_input_digest(monkeypatch):
    """A second call with equal inputs (other array objects) returns the first result without looking anything
    up; a change to any input is looked up again and gives its own result; only the last few results are kept."""
    from hte_jax.hbr import middle

    lookups = []

    def counting(*args, **kwargs):
        lookups.append(args[2].shape)
        return nearest_index(*args, **kwargs)

    rng = np.random.default_rng(11)
    cells, capacity = 200, 40
    arrays = dict(genotypes=rng.uniform(size=(cells, 6)).astype(np.float32),
                  descriptors=rng.uniform(size=(cells, 3)).astype(np.float32), filled=rng.uniform(size=cells) < 0.7)
    bottom = Repertoire(fitnesses=jnp.zeros(cells), **{k: jnp.asarray(v) for k, v in arrays.items()})
    genotypes = rng.uniform(size=(capacity, 18)).astype(np.float32)
    filled = rng.uniform(size=capacity) < 0.5
    moved = genotypes.copy()
    moved[np.flatnonzero(filled)[0]] = 1.0 - moved[np.flatnonzero(filled)[0]]
    expected = np.asarray(jnp.where(jnp.asarray(filled)[:, None], leg_controllers(bottom, decode(jnp.asarray(moved))), 0.0))
    monkeypatch.setattr(middle, "_nearest_index", counting)  # the jitted lookup of concrete inputs
    monkeypatch.setattr(middle, "_elite_cache", type(middle._elite_cache)())  # the process's own entries stay

    first = np.asarray(elite_controllers(bottom, jnp.asarray(genotypes), jnp.asarray(filled)))
    assert len(lookups) == 1
    again = elite_controllers(Repertoire(fitnesses=jnp.ones(cells), **{k: jnp.asarray(v.copy()) for k, v in arrays.items()}),
                              jnp.asarray(genotypes.copy()), jnp.asarray(filled.copy()))
    assert len(lookups) == 1  # equal inputs: no lookup (the fitnesses play no part)
    np.testing.assert_array_equal(np.asarray(again), first)

    other = np.asarray(elite_controllers(bottom, jnp.asarray(moved), jnp.asarray(filled)))
    assert len(lookups) == 2 and not np.array_equal(other, first)
    np.testing.assert_array_equal(other, expected)
    fewer_bottom = bottom.replace(filled=bottom.filled.at[int(np.flatnonzero(arrays["filled"])[0])].set(False))
    elite_controllers(fewer_bottom, jnp.asarray(genotypes), jnp.asarray(filled))
    assert len(lookups) == 3  # the bottom layer is part of the key

    for i in range(middle.ELITE_CACHE_SIZE):  # as many other inputs as are kept push the first out
        elite_controllers(bottom, jnp.asarray(genotypes + np.float32(i + 1) / 64), jnp.asarray(filled))
    assert len(middle._elite_cache) == middle.ELITE_CACHE_SIZE
    count = len(lookups)
    np.testing.assert_array_equal(np.asarray(elite_controllers(bottom, jnp.asarray(genotypes), jnp.asarray(filled))), first)
    assert len(lookups) == count + 1


def test_contact_pattern_codes():
    bits = jnp.asarray([[1, 1, 1, 1, 1, 1], [0, 1, 1, 1, 1, 1], [1, 0, 1, 0, 1, 0], [0, 0, 0, 0, 0, 1]], jnp.float32)
    codes = np.asarray(pattern_code(bits))
    np.testing.assert_array_equal(codes, [63, 31, 42, 1])  # leg 0 is the most significant bit (original)
    np.testing.assert_array_equal(np.asarray(pattern_bits(jnp.asarray(codes))), np.asarray(bits))


def test_select_middle_respects_patterns():
    rng = np.random.default_rng(4)
    capacity = 64
    middle = empty_repertoire(capacity, 18, 9)
    desc = rng.uniform(size=(40, 9)).astype(np.float32)
    desc[:, 3:] = np.asarray(pattern_bits(jnp.asarray(rng.choice([63, 42, 21], size=40))))
    middle = middle.replace(descriptors=middle.descriptors.at[:40].set(desc), filled=middle.filled.at[:40].set(True),
                            fitnesses=middle.fitnesses.at[:40].set(0.0))
    bottom = empty_repertoire(8, 6, 3).replace(filled=jnp.ones(8, bool))
    hbr = HBR.build(bottom, middle, empty_repertoire(4, 9, 2), MiddleTask())
    queries = rng.uniform(size=(30, 3)).astype(np.float32)
    patterns = rng.choice([-1, 63, 42, 21, 0], size=30)
    index, found = (np.asarray(x) for x in select_middle(hbr, jnp.asarray(queries), jnp.asarray(patterns), chunk=8))
    codes = np.asarray(pattern_code(jnp.asarray(desc[:, 3:])))
    for q, p, i, f in zip(queries, patterns, index, found):
        allowed = np.ones(40, bool) if p < 0 or p == 0 else codes == p
        d = np.where(allowed, ((desc[:, :3] - q) ** 2).sum(-1), np.inf)
        assert i == np.argmin(d)
        assert f == (p != 0)  # pattern 0 (no foot down) has no elite: nearest of any pattern


def test_skill_waypoints_compose_middle_steps():
    task = MiddleTask()
    # Step 1: 0.2 m forward turning +0.5 rad; step 2: 0.1 m forward; step 3: 0.1 m left, no turn.
    steps = np.array([[0.2, 0.0, 0.5], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    genes = np.asarray(task.normalise(jnp.asarray(steps))).reshape(9)
    waypoints = np.asarray(skill_waypoints(task, jnp.asarray(genes)))
    expected1 = np.array([0.2, 0.0, 0.5])
    expected2 = expected1 + [0.1 * math.cos(0.5), 0.1 * math.sin(0.5), 0.0]
    expected3 = expected2 + [-0.1 * math.sin(0.5), 0.1 * math.cos(0.5), 0.0]
    np.testing.assert_allclose(waypoints, [expected1, expected2, expected3], atol=1e-6)


def test_speed_by_turn_hand_case():
    """Motions (x, y, yaw) -> speed per |yaw| bin; empty slots ignored, the last bin includes max_turn."""
    task = MiddleTask()
    steps = jnp.asarray([[0.3, 0.4, 0.05], [0.1, 0.0, -0.95], [0.0, 0.2, 1.0], [0.1, 0.1, 0.02], [0.45, 0.0, 0.0]])
    middle = empty_repertoire(5, 18, 9).replace(
        descriptors=jnp.concatenate([task.normalise(steps), jnp.ones((5, 6))], axis=1),
        filled=jnp.asarray([True, True, True, True, False]),
    )
    rows = speed_by_turn(SimpleNamespace(middle=middle, middle_task=task), bins=10)
    assert [row["motions"] for row in rows] == [2, 0, 0, 0, 0, 0, 0, 0, 0, 2]
    assert rows[0]["speed_max"] == pytest.approx(0.5, abs=1e-6)
    assert rows[9]["speed_max"] == pytest.approx(0.2, abs=1e-6)
    assert rows[9]["speed_p95"] == pytest.approx(np.percentile([0.1, 0.2], 95), abs=1e-6)
    assert rows[1]["speed_max"] is None and rows[1]["speed_p95"] is None and rows[9]["turn"] == [0.9, 1.0]


def test_fitness_by_distance_hand_case():
    """Skills ending at known distances fall in the right bands; empty slots and empty bands are skipped."""
    task = TopTask()
    ends = jnp.asarray([[0.1, 0.0], [0.0, -0.2], [0.4, 0.3], [-0.7, 0.0], [1.0, 1.0], [0.05, 0.05]])
    top = empty_repertoire(6, 9, 2).replace(
        descriptors=task.normalise(ends),
        fitnesses=jnp.asarray([-0.1, -0.3, -0.5, -1.0, -2.0, -9.0]),
        filled=jnp.asarray([True, True, True, True, True, False]),
    )
    rows = fitness_by_distance(SimpleNamespace(top=top), task, edges=(0.0, 0.3, 0.6, 0.9, 1.2, float("inf")))
    assert [row["cells"] for row in rows] == [2, 1, 1, 0, 1]
    assert rows[0]["mean_fitness"] == pytest.approx(-0.2) and rows[1]["mean_fitness"] == pytest.approx(-0.5)
    assert rows[3]["mean_fitness"] is None and rows[4]["distance"] == [1.2, None]
    assert rows[4]["mean_fitness"] == pytest.approx(-2.0)


@pytest.mark.slow
def test_middle_purity_penalises_contact_on_lifted_legs():
    """fitness(purity) = fitness(0) - purity * sum of the contact fractions of the legs whose bit is 0."""
    import jax
    from hte_jax.hbr.middle import MiddleTask, evaluate_controllers
    from hte_jax.sim.robot import load_robot
    from hte_jax.sim.rollout import standing_state

    robot = load_robot()
    start = standing_state(robot)
    params = jax.numpy.asarray(np.random.default_rng(3).uniform(size=(3, 36)), jax.numpy.float32)
    plain = evaluate_controllers(robot, start, MiddleTask(samples=2, steps=20), params)
    pure = evaluate_controllers(robot, start, MiddleTask(samples=2, steps=20, purity=4.0), params)
    fraction, bits = np.asarray(plain.extras["contact_fraction"]), np.asarray(plain.descriptors)[:, 3:]
    expected = np.asarray(plain.fitnesses) - 4.0 * (fraction * (1.0 - bits)).sum(axis=-1)
    np.testing.assert_allclose(np.asarray(pure.fitnesses), expected, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(pure.descriptors), np.asarray(plain.descriptors))


@pytest.mark.slow
def test_leg_primitives_hand_cases(robot):
    """A leg that never lifts has height ~ 0; lifting and stroking legs are measured as such on every leg."""
    still = [0.0, 0.3, 0.5, 0.0, 0.2, 0.5]  # zero amplitudes
    lift = [0.0, 0.0, 0.5, 1.0, 0.0, 0.5]  # vertical signal only: the foot goes up and down
    stroke = [1.0, 0.0, 0.5, 1.0, 0.25, 0.5]  # hip swing with the lift a quarter period later
    genes = jnp.asarray([still] * 6 + [lift] * 6 + [stroke] * 6 + [[-1.0] * 6], jnp.float32)
    task = BottomTask()
    # A fixed key; the leg drawn for each row is recomputed the same way to check every leg is covered.
    evaluation = jax.jit(lambda k, g: evaluate_bottom(robot, standing_state(robot), task, k, g))(jax.random.PRNGKey(7), genes)
    legs = np.asarray(evaluation.extras["leg"])
    desc = np.asarray(evaluation.descriptors)
    swing = desc[:, 0] * 2 * task.swing_range - task.swing_range
    height = desc[:, 1] * 2 * task.height_range - task.height_range
    assert np.asarray(evaluation.valid)[:18].all()
    assert np.abs(height[:6]).max() < 0.002 and np.abs(swing[:6]).max() < 0.002
    assert (height[6:12] > 0.02).all()
    assert np.abs(swing[6:12]).max() < 0.01  # no hip motion: no stroke
    assert (np.abs(swing[12:18]) > 0.03).all() and np.ptp(swing[12:18]) < 0.02  # same stroke on every leg
    fitness = np.asarray(evaluation.fitnesses)
    assert fitness[:6].max() > fitness[6:12].max() > fitness[12:18].max()  # more motion, more activation
    assert len(set(legs[:18].tolist())) > 1
