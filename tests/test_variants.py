"""The variant table and the pattern rules: each rule chooses and learns its own way, a batch runs
only its variants' rules, and no rule but the oracle reads the damage (tests/test_extending.py runs
a new rule through maze_eval)."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.online import variants
from hte_jax.online.gp import add_observation
from hte_jax.online.rules import (
    CANDIDATE_PATTERNS,
    AnyPattern,
    GpUcb,
    Oracle,
    RandomPattern,
    SensedLegs,
    StepContext,
    StepObservation,
    candidate_elites,
    choose_patterns,
    learn_rules,
    start_rules,
)
from hte_jax.online.secondary import oracle_pattern
from hte_jax.online.sensing import JOINT_EVIDENCE, JOINT_RATIO, stuck_legs
from hte_jax.sim.damage import paper_damage_masks

FORWARD = [0.7, 0.5, 0.5]  # 0.2 m forward, no turn (normalised)


def _context(hbr, batch, seed=0, t=1):
    return StepContext(hbr=hbr, desired=jnp.asarray([FORWARD] * batch), t=jnp.full(batch, t, jnp.int32),
                       keys=jax.random.split(jax.random.PRNGKey(seed), batch))


def test_the_table_holds_the_paper_variants_and_ours():
    assert list(variants.VARIANTS) == ["hte", "perfect-hte", "random-hte", "rte", "hte-spare", "perfect-spare",
                                       "rte-spare", "hte-sense", "2d-rte", "8d-rte", "aprol"]
    for name, entry in variants.VARIANTS.items():
        assert entry.name == name and entry.summary and entry.hierarchical == (entry.repertoire == "hbr")
    assert [name for name, v in variants.VARIANTS.items() if v.spares] == ["hte-spare", "perfect-spare", "rte-spare"]
    # the ablation: hte-spare's sensing without its spare sets, a rule of its own in a batch beside hte-spare
    assert variants.variant("hte-sense").rule == SensedLegs() != variants.variant("hte-spare").rule
    assert variants.batch_rules(["hte-spare", "hte-sense", "hte-spare"])[1] == [0, 1, 0]
    with pytest.raises(ConfigError, match="unknown variant"):
        variants.variant("hte-psychic")
    with pytest.raises(ConfigError, match="already defined"):
        variants.add_variant(variants.Variant("hte", GpUcb(), summary="again"))
    with pytest.raises(ConfigError, match="PatternRule"):
        variants.add_variant(variants.Variant("hte-x", "gp-ucb", summary="a name is not a rule"))
    with pytest.raises(ConfigError, match="no contact patterns"):
        variants.add_variant(variants.Variant("flat-x", GpUcb(), repertoire="2d", summary="flat with a rule"))


def test_a_batch_holds_each_distinct_rule_once():
    rules, which = variants.batch_rules(["rte", "hte", "rte", "perfect-hte", "perfect-spare", "hte", "2d-rte"])
    assert rules == (AnyPattern(), GpUcb(), Oracle(), Oracle(spare=True))
    assert which == [0, 1, 0, 2, 3, 1, 0]


def test_every_rule_chooses_in_the_documented_shapes(shipped_hbr):
    hbr, _ = shipped_hbr
    damages = paper_damage_masks()[:5]
    rules = (AnyPattern(), GpUcb(), Oracle(), RandomPattern(), SensedLegs(spare=True), AnyPattern(spare=True))
    damages = np.concatenate([damages, damages[:1]])
    batch = start_rules(rules, np.arange(6), damages, max_actions=4)
    assert batch.states[1].gp.mask.shape == (6, 12)  # three steps per action
    pattern, spare = choose_patterns(batch, _context(hbr, 6))
    chex.assert_shape([pattern, spare], [(6,), (6,)])
    chex.assert_type([pattern, spare], [jnp.int32, bool])
    pattern = np.asarray(pattern)
    assert pattern[0] == -1 and pattern[2] == oracle_pattern(damages[2]) and pattern[4] == -1 and pattern[5] == -1
    assert pattern[1] in CANDIDATE_PATTERNS and pattern[3] in CANDIDATE_PATTERNS
    # nothing sensed yet; the plain oracle does not spare; rte-spare's rule always looks among the spare elites
    assert np.asarray(spare).tolist() == [False] * 5 + [True]
    with pytest.raises(ValueError, match="rule indices"):
        start_rules(rules, np.array([6]), damages[:1], 4)


def test_gp_ucb_starts_at_the_lowest_pattern_and_leaves_one_seen_to_fail(shipped_hbr):
    hbr, _ = shipped_hbr
    rule = GpUcb()
    state = rule.init(np.zeros((1, 6), bool), 4)
    context = _context(hbr, 1)
    index, found = candidate_elites(hbr, context.desired)
    lowest = int(CANDIDATE_PATTERNS[np.argmax(np.asarray(found[0]))])
    assert int(rule.choose(state, context)[0][0]) == lowest  # an empty GP scores alike: the first wins, as in the original
    bad = hbr.middle.descriptors[index[0, np.argmax(np.asarray(found[0]))]]
    gp = jax.tree.map(lambda x: x[0], state.gp)
    for _ in range(3):
        gp = add_observation(gp, bad, jnp.asarray([3.0, 3.0, 3.0]))
    failed = state.replace(gp=jax.tree.map(lambda x: x[None], gp))
    assert int(rule.choose(failed, _context(hbr, 1, t=4))[0][0]) != lowest


def test_random_patterns_cover_many_of_the_allowed_ones(shipped_hbr):
    hbr, _ = shipped_hbr
    rule = RandomPattern()
    draws = {int(rule.choose(rule.init(np.zeros((1, 6), bool), 1), _context(hbr, 1, seed=k))[0][0]) for k in range(20)}
    assert len(draws) > 5 and draws <= set(CANDIDATE_PATTERNS.tolist())


def test_sensed_legs_lifts_a_leg_off_the_floor_or_one_that_does_not_follow(shipped_hbr):
    hbr, _ = shipped_hbr
    rule = SensedLegs(spare=True)
    state = rule.init(np.zeros((5, 6), bool), 4)
    contacts = np.zeros((5, 2, 6), np.float32)
    contacts[:, 1], contacts[:, 0] = 0.8, 0.9  # every foot touched the floor as expected
    motion = np.zeros((5, 2, 6), np.float32)
    motion[:, 1], motion[:, 0] = 4.0, 3.6  # 4 rad commanded to every leg, 3.6 moved
    motion[1, 0, 1] = 0.3  # robot 1's leg 1 hardly moved (locked on the floor)
    motion[2, 0, 4] = 0.3  # robot 2's leg 4 too, but it was asked less than the evidence needs
    motion[2, 1, 4] = 0.5 * JOINT_EVIDENCE
    contacts[3, 0, 2] = 0.0  # robot 3's leg 2 never touched the floor
    contacts[4, 1, 5] = 0.2  # robot 4's leg 5 off the floor, but too little was expected of it to tell
    contacts[4, 0, 5] = 0.0
    state = state.replace(contacts=jnp.asarray(contacts), motion=jnp.asarray(motion))
    pattern, spare = rule.choose(state, _context(hbr, 5))
    assert np.asarray(pattern).tolist() == [-1, 63 - (1 << 4), -1, 63 - (1 << 3), -1]
    assert np.asarray(spare).tolist() == [False, False, False, True, False]  # only a leg off the floor is spared
    plain = SensedLegs()
    assert not np.asarray(plain.choose(state, _context(hbr, 5))[1]).any()


def test_stuck_legs_against_numpy():
    rng = np.random.default_rng(0)
    motion = rng.uniform(0.0, 2.0 * JOINT_EVIDENCE, (50, 2, 6)).astype(np.float32)
    expected = (motion[:, 1] >= JOINT_EVIDENCE) & (motion[:, 0] < JOINT_RATIO * motion[:, 1])
    assert 0 < expected.sum() < expected.size
    np.testing.assert_array_equal(stuck_legs(jnp.asarray(motion)), expected)


def test_sensed_legs_learns_what_the_step_sensed_beside_what_its_elite_expected(shipped_hbr):
    hbr, _ = shipped_hbr
    rule = SensedLegs()
    state = rule.init(np.zeros((2, 6), bool), 4)
    elite = jnp.asarray(np.flatnonzero(np.asarray(hbr.middle.filled))[:2], jnp.int32)
    sensed = jnp.asarray([[1.0, 0.0, 1.0, 1.0, 1.0, 1.0], [0.5] * 6], jnp.float32)
    travel = jnp.full((2, 6), 0.25, jnp.float32)
    observation = StepObservation(hbr=hbr, elite=elite, observed=jnp.zeros((2, 3)), contact_fraction=sensed,
                                  leg_travel=travel)
    learnt = rule.learn(rule.learn(state, observation), observation)
    np.testing.assert_allclose(learnt.contacts[:, 0], 2 * sensed)
    np.testing.assert_allclose(learnt.contacts[:, 1], 2 * hbr.middle.extras["contact_fraction"][elite])
    np.testing.assert_allclose(learnt.motion[:, 0], 2 * travel)
    assert (np.asarray(learnt.motion[:, 1]) > 0).all()  # the elites' controllers command every joint


@pytest.mark.slow
def test_no_rule_but_the_oracle_reads_the_damage(shipped_hbr):
    """The same batch, with the damages handed to the rules permuted, makes the same choices and
    learns the same states for every rule but the oracle (the robot does not know its damage)."""
    hbr, _ = shipped_hbr
    damages = paper_damage_masks()
    rules = (AnyPattern(), GpUcb(), RandomPattern(), SensedLegs(spare=True), Oracle())
    which = np.arange(7) % len(rules)
    permuted = damages[::-1]
    elite = jnp.asarray(np.flatnonzero(np.asarray(hbr.middle.filled))[:7], jnp.int32)
    rng = np.random.default_rng(3)
    observation = StepObservation(hbr=hbr, elite=elite, observed=jnp.asarray(rng.uniform(0.3, 0.7, (7, 3)), jnp.float32),
                                  contact_fraction=jnp.asarray(rng.uniform(0, 1, (7, 6)), jnp.float32),
                                  leg_travel=jnp.asarray(rng.uniform(0, 2, (7, 6)), jnp.float32))
    runs = []
    for given in (damages, permuted):
        batch = start_rules(rules, which, given, max_actions=3)
        choices = []
        for step in range(3):
            choices.append(choose_patterns(batch, _context(hbr, 7, seed=step, t=step + 1)))
            batch = learn_rules(batch, observation)
        runs.append((choices, batch))
    (first, first_batch), (second, second_batch) = runs
    not_oracle = which != 4
    for (p1, s1), (p2, s2) in zip(first, second):
        np.testing.assert_array_equal(np.asarray(p1)[not_oracle], np.asarray(p2)[not_oracle])
        np.testing.assert_array_equal(np.asarray(s1)[not_oracle], np.asarray(s2)[not_oracle])
    for rule, a, b in zip(rules[:4], first_batch.states[:4], second_batch.states[:4]):
        chex.assert_trees_all_equal(a, b)
    # the oracle does read it: the permuted damages move its patterns
    oracle_rows = np.flatnonzero(which == 4)
    assert (np.asarray(first[0][0])[oracle_rows] != np.asarray(second[0][0])[oracle_rows]).any()


def test_the_oracle_keeps_the_damaged_legs_off_whatever_their_model():
    """Episodes started with a `Damage` per row: the oracle's pattern has the damaged legs up whatever their damage
    model, and a damage of the floor alone damages no leg; the episodes keep the damage."""
    from hte_jax.flat.store import load_flat, shipped_flat_path
    from hte_jax.online.episode import AdaptationConfig, start_episodes
    from hte_jax.online.skills import flat_skills
    from hte_jax.sim.damage import damage_mask, parse_damages, stack_damages

    flat, _ = load_flat(shipped_flat_path("2d"))
    spelled = parse_damages("leg0:removed,leg1:shortened=0.5:friction=0.6,none:friction=0.5,legs1+4:weak=0.3")
    damage = stack_damages(spelled.values())
    episodes = start_episodes(AdaptationConfig(max_actions=2), flat_skills(flat[0], flat.task.extent),
                              jnp.zeros((4, 3)), damage, (Oracle(),), np.zeros(4, np.int32), jax.random.PRNGKey(0))
    expected = [oracle_pattern(damage_mask(legs)) for legs in ([0], [1], [], [1, 4])]
    assert expected[2] == 0b111111
    np.testing.assert_array_equal(episodes.rules.states[0].pattern, expected)
    for field in ("legs", "model", "fraction", "friction"):
        np.testing.assert_array_equal(getattr(episodes.damage, field), getattr(damage, field))
