"""Sparing sets (hte_jax.hbr.sparing): membership against a NumPy brute force, a second archive
appended without changing any lookup of the HBR's own, planned steps that keep the lifted legs off
the floor, and the variants that execute from them."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.hbr.composition import plan_batch
from hte_jax.hbr.hierarchy import select_middle
from hte_jax.hbr.sparing import STRICT_CONTACT, lifted_legs, sparing_members, sparing_table, with_spare
from hte_jax.online import variants
from hte_jax.online.execute import hbr_skills
from hte_jax.online.secondary import unusable_legs


def test_lifted_legs_reads_the_pattern_bits():
    assert lifted_legs(np.array(63)).tolist() == [False] * 6
    assert lifted_legs(np.array(0b101111)).tolist() == [False, True, False, False, False, False]
    assert lifted_legs(np.array(0b101101)).tolist() == [False, True, False, False, True, False]


def test_members_match_a_brute_force():
    rng = np.random.default_rng(0)
    fraction = rng.choice([0.0, 0.02, 0.04, 0.05, 0.2, 0.6], size=(40, 6))
    present = rng.random(40) > 0.2
    members = sparing_members(fraction, present, 0.05)
    for p in range(64):
        lifted = [leg for leg in range(6) if not (p >> (5 - leg)) & 1]
        expected = [bool(present[e]) and all(fraction[e, leg] < 0.05 for leg in lifted) for e in range(40)]
        assert members[p].tolist() == expected, p
    assert members[63].tolist() == present.tolist()  # nothing lifted: every usable elite


def test_spare_elites_join_only_the_sparing_sets(shipped_hbr):
    hbr, _ = shipped_hbr
    own = int(hbr.middle.capacity)
    spare = jax.tree.map(lambda x: x[:own], hbr.middle)  # the HBR's own elites as a stand-in archive
    fraction = np.asarray(spare.extras["contact_fraction"]).copy()
    fraction[:, 1] = 0.0  # every stand-in keeps leg 1 off the floor
    spare = spare.replace(extras={**spare.extras, "contact_fraction": jnp.asarray(fraction)})
    joined = with_spare(hbr, spare, hbr.middle_params, hbr.step_model)
    added = int(np.asarray(hbr.middle.filled).sum())
    assert joined.spare_count == added and joined.middle.capacity == own + added
    # the HBR's own lookups never see the appended elites
    queries = jax.random.uniform(jax.random.key(1), (32, 3))
    for pattern in (-1, 0b101111, 63):
        wanted = jnp.full(32, pattern, jnp.int32)
        np.testing.assert_array_equal(select_middle(joined, queries, wanted)[0], select_middle(hbr, queries, wanted)[0])
    np.testing.assert_array_equal(joined.middle_patterns[own:], -1)
    # their contact bits are re-computed at the HBR's threshold, their controllers kept
    bits = np.asarray(joined.middle.descriptors[own:, 3:])
    np.testing.assert_array_equal(bits, fraction[np.asarray(hbr.middle.filled)] > hbr.middle_task.contact_threshold)
    np.testing.assert_array_equal(joined.middle_params[own:], hbr.middle_params[np.asarray(hbr.middle.filled)])
    # leg 1's sparing set: the HBR's own elites under 5 % on leg 1 plus every appended one
    table = sparing_table(joined)
    row = np.asarray(table.index[0b101111])
    row = row[row >= 0]
    own_members = np.flatnonzero(np.asarray(hbr.middle.filled) & (np.asarray(hbr.middle.extras["contact_fraction"])[:, 1] < STRICT_CONTACT))
    np.testing.assert_array_equal(np.sort(row), np.concatenate([own_members, own + np.arange(added)]))


def test_planned_sparing_steps_keep_the_lifted_legs_off_the_floor(shipped_hbr):
    hbr, top_task = shipped_hbr
    table = sparing_table(hbr)
    fraction = np.asarray(hbr.middle.extras["contact_fraction"])
    here = jnp.zeros((6, 3))
    target = jnp.asarray([[0.3, 0.0, 0.0], [0.2, 0.2, 0.3], [-0.2, 0.0, 0.0]] * 2)
    pattern = jnp.asarray([0b101111] * 3 + [0b111101] * 3, jnp.int32)
    elite = np.asarray(plan_batch(table, hbr.middle_task, here, target, pattern, 3))
    assert (elite >= 0).all()
    assert (fraction[elite[:3], 1] < STRICT_CONTACT).all() and (fraction[elite[3:], 4] < STRICT_CONTACT).all()


def test_sparing_variants_are_table_entries_that_need_planned_composition(shipped_hbr):
    hbr, top_task = shipped_hbr
    assert variants.variant("hte-spare").sparing == "off-floor" and variants.variant("hte-spare").rule == "sensed"
    assert variants.variant("hte-spare-always").sparing == "always"
    assert variants.variant("perfect-spare").sparing == "always" and variants.variant("perfect-spare").rule == "oracle"
    assert not any(v.spares for name, v in variants.VARIANTS.items() if name in ("hte", "rte", "perfect-hte"))
    with pytest.raises(ConfigError, match="no contact patterns"):
        variants.add_variant(variants.Variant("flat-spare", repertoire="2d", sparing="always", summary="x"))
    with pytest.raises(ConfigError, match="sparing 'sometimes' is not one of"):
        variants.add_variant(variants.Variant("odd-spare", "sensed", sparing="sometimes", summary="x"))
    with pytest.raises(ConfigError, match="composition planned"):
        hbr_skills(hbr, top_task, composition="waypoints", sparing=True)
    assert hbr_skills(hbr, top_task).sparing is None
    assert hbr_skills(hbr, top_task, sparing=True).sparing is not None


def test_spares_now_follows_each_episodes_sparing_mode_and_sensed_contacts():
    # episodes: never, always, off-floor with a leg sensed off the floor (leg 2 expected 1 s,
    # sensed none), off-floor with every leg touching as expected (a locked leg), off-floor with
    # too little evidence yet (0.2 s expected)
    contacts = np.zeros((5, 2, 6), np.float32)
    contacts[:, 1, :] = 1.0
    contacts[:, 0, :] = 1.0
    contacts[2, 0, 2] = 0.0
    contacts[4] = 0.2
    contacts[4, 0, 2] = 0.0
    never, always, off_floor = (variants.SPARING.index(m) for m in ("never", "always", "off-floor"))
    learnt = variants.PatternState(mode=None, oracle=None, optimism=None, secondary=None,
                                   contacts=jnp.asarray(contacts), motion=None,
                                   sparing=jnp.asarray([never, always, off_floor, off_floor, off_floor], jnp.int32),
                                   measured=None, last=None)
    off = np.asarray(unusable_legs(jnp.asarray(contacts))).any(axis=-1)
    assert off.tolist() == [False, False, True, False, False]
    np.testing.assert_array_equal(np.asarray(variants.spares_now(learnt)), [False, True, True, False, False])


def test_the_set_of_the_pattern_lifting_no_leg_is_its_own_elites(shipped_hbr):
    hbr, _ = shipped_hbr
    row = np.asarray(sparing_table(hbr).index[63])
    np.testing.assert_array_equal(np.sort(row[row >= 0]), np.flatnonzero(np.asarray(hbr.middle_patterns) == 63))


def test_train_spare_writes_an_archive_tied_to_its_bottom_layer(shipped_hbr, tmp_path):
    from experiments.pattern_ends import main as ends_main
    from experiments.train_spare import main as spare_main
    from hte_jax.hbr.store import load_spare
    from hte_jax.qd.io import CheckpointError

    def read_json(path):
        return json.loads(path.read_text())

    hbr, _ = shipped_hbr
    assert spare_main(["--threshold", "1.5", "--out", str(tmp_path / "bad")]) == 2
    assert ends_main(["--max-lifted", "0"]) == 2
    out = tmp_path / "spare"
    assert spare_main(["--preset", "tiny", "--out", str(out), "--no-progress"]) == 0
    summary = read_json(out / "summary.json")
    joined = load_spare(out / "spare.npz", hbr)
    assert joined.spare_count == summary["elites"] > 0
    own = int(hbr.middle.capacity)
    fraction = np.asarray(joined.middle.extras["contact_fraction"][own:])
    bits = np.asarray(joined.middle.descriptors[own:, 3:])
    np.testing.assert_array_equal(bits, fraction > hbr.middle_task.contact_threshold)  # the HBR's threshold
    assert summary["threshold"] == STRICT_CONTACT and summary["lifting_each_leg"]["spare"] == (fraction < STRICT_CONTACT).sum(axis=0).tolist()
    assert spare_main(["--preset", "tiny", "--out", str(out), "--no-progress"]) == 2  # the folder holds a run
    other = hbr.replace(bottom=hbr.bottom.replace(genotypes=hbr.bottom.genotypes + 0.01))
    with pytest.raises(CheckpointError, match="another HBR's bottom layer"):
        load_spare(out / "spare.npz", other)
