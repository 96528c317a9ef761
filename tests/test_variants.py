"""The variant table: every variant is one entry, rules are integers in jitted code, and every rule
gets a context of the documented shapes (tests/test_extending.py runs a new variant through maze_eval)."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.hbr.store import load_hbr
from hte_jax.online import variants
from hte_jax.online.episode import variant_mode
from hte_jax.online.execute import CONTACTS_MODE, SECONDARY_OUTPUTS, choose_patterns
from hte_jax.online.secondary import JOINT_EVIDENCE, JOINT_RATIO, stuck_legs
from hte_jax.online.gp import empty_gp


def test_the_table_names_every_variant_once_with_a_known_rule():
    assert {"hte", "perfect-hte", "random-hte", "rte", "2d-rte", "8d-rte", "aprol", "hte-contacts"} <= set(variants.VARIANTS)
    for name, entry in variants.VARIANTS.items():
        assert entry.name == name and entry.rule in variants.RULES and entry.summary
        assert entry.hierarchical == (entry.repertoire == "hbr")
    assert variant_mode("rte", True) == variant_mode("2d-rte", False) == 0  # flat variants run RTE's rule
    with pytest.raises(ConfigError, match="needs an HBR"):
        variant_mode("hte", False)
    with pytest.raises(ConfigError, match="unknown variant"):
        variants.variant("hte-psychic")
    with pytest.raises(ConfigError, match="already defined"):
        variants.add_variant(variants.Variant("hte", "gp-ucb", summary="again"))
    with pytest.raises(ConfigError, match="unknown rule"):
        variants.add_variant(variants.Variant("hte-x", "psychic", summary="no such rule"))
    with pytest.raises(ConfigError, match="no contact patterns"):
        variants.add_variant(variants.Variant("flat-x", "gp-ucb", repertoire="2d", summary="flat with a rule"))


def test_contacts_rule_is_rte_until_a_leg_stays_off_the_floor():
    hbr, _, _ = load_hbr()
    desired = jnp.asarray([[0.7, 0.5, 0.5]] * 2)
    gp = jax.tree.map(lambda x: jnp.broadcast_to(x, (2, *x.shape)), empty_gp(6, 9, SECONDARY_OUTPUTS))
    modes = jnp.full(2, CONTACTS_MODE, jnp.int32)
    contacts = np.zeros((2, 2, 6), np.float32)
    contacts[:, 1] = 0.8  # every leg expected down 0.8 s
    contacts[:, 0] = 0.9
    contacts[1, 0, 4] = 0.0  # robot 1's leg 4 never touched the floor
    chosen, query = choose_patterns(hbr, modes, jnp.asarray([63, 63]), gp, desired, jnp.ones(2, jnp.int32),
                                    jax.random.split(jax.random.PRNGKey(0), 2), contacts=jnp.asarray(contacts))
    assert np.asarray(chosen).tolist() == [-1, 63 - (1 << 1)]
    np.testing.assert_array_equal(query, desired)


def test_sensed_rule_also_lifts_a_leg_whose_joints_do_not_follow_their_commands():
    hbr, _, _ = load_hbr()
    batch = 4
    desired = jnp.asarray([[0.7, 0.5, 0.5]] * batch)
    gp = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), empty_gp(6, 9, SECONDARY_OUTPUTS))
    contacts = np.zeros((batch, 2, 6), np.float32)
    contacts[:, 1], contacts[:, 0] = 0.8, 0.9  # every foot touched the floor as expected
    motion = np.zeros((batch, 2, 6), np.float32)
    motion[:, 1] = 4.0  # 4 rad commanded to every leg
    motion[:, 0] = 3.6
    motion[1, 0, 1] = 0.3  # robot 1's leg 1 hardly moved (locked on the floor)
    motion[2, 0, 4] = 0.3  # robot 2's leg 4 too, but it was asked less than the evidence needs
    motion[2, 1, 4] = 0.5 * JOINT_EVIDENCE
    contacts[3, 0, 2] = 0.0  # robot 3's leg 2 never touched the floor: the contacts still count
    modes = jnp.full(batch, variants.rule_index("sensed"), jnp.int32)
    chosen, query = choose_patterns(hbr, modes, jnp.full(batch, 63), gp, desired, jnp.ones(batch, jnp.int32),
                                    jax.random.split(jax.random.PRNGKey(0), batch), contacts=jnp.asarray(contacts),
                                    motion=jnp.asarray(motion))
    assert np.asarray(chosen).tolist() == [-1, 63 - (1 << 4), -1, 63 - (1 << 3)]
    np.testing.assert_array_equal(query, desired)
    # the contacts rule alone does not see the locked leg
    contacts_only = choose_patterns(hbr, jnp.full(batch, CONTACTS_MODE, jnp.int32), jnp.full(batch, 63), gp, desired,
                                    jnp.ones(batch, jnp.int32), jax.random.split(jax.random.PRNGKey(0), batch),
                                    contacts=jnp.asarray(contacts), motion=jnp.asarray(motion))[0]
    assert np.asarray(contacts_only).tolist() == [-1, -1, -1, 63 - (1 << 3)]


def test_stuck_legs_against_numpy():
    rng = np.random.default_rng(0)
    motion = rng.uniform(0.0, 2.0 * JOINT_EVIDENCE, (50, 2, 6)).astype(np.float32)
    expected = (motion[:, 1] >= JOINT_EVIDENCE) & (motion[:, 0] < JOINT_RATIO * motion[:, 1])
    assert 0 < expected.sum() < expected.size
    np.testing.assert_array_equal(stuck_legs(jnp.asarray(motion)), expected)


def test_every_rule_sees_a_context_of_the_documented_shapes():
    hbr, _, _ = load_hbr()
    batch = 3
    gp = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), empty_gp(6, 9, SECONDARY_OUTPUTS))
    ctx = variants.step_context(hbr, jnp.full((batch, 3), 0.5), jnp.ones(batch, jnp.int32),
                                jax.random.split(jax.random.PRNGKey(0), batch), jnp.full(batch, 63, jnp.int32),
                                jnp.zeros(batch), gp, jnp.zeros((batch, 2, 6)), jnp.zeros((batch, 2, 6)))
    chex.assert_shape([ctx.every, ctx.found, ctx.variance], (batch, 64))
    chex.assert_shape([ctx.inputs, ctx.mean], (batch, 64, 9))
    chex.assert_type([ctx.every, ctx.found], [jnp.int32, bool])
    chex.assert_shape([ctx.contacts, ctx.motion], (batch, 2, 6))
    for name, rule in variants.RULES.items():
        pattern, query = rule(ctx)
        chex.assert_shape(pattern, (batch,))
        chex.assert_type(pattern, jnp.int32)
        assert query is None or query.shape == (batch, 3), name
        assert ((np.asarray(pattern) >= -1) & (np.asarray(pattern) < 64)).all(), name
    modes = jnp.arange(batch, dtype=jnp.int32) % len(variants.RULES)
    pattern, query = variants.choose(ctx, modes)
    chex.assert_shape([pattern, query], [(batch,), (batch, 3)])
