"""Checking the (skill, pattern) pairs that modulation and the measured pattern ends re-execute."""

import numpy as np
import pytest

from hte_jax.hbr.composition import skill_ends
from hte_jax.hbr.modulation import checked_pairs, stored_ends


def test_defaults_are_every_filled_skill_and_every_pattern(shipped_hbr):
    hbr, _ = shipped_hbr
    slots, patterns = checked_pairs(hbr, None, None)
    np.testing.assert_array_equal(slots, np.flatnonzero(np.asarray(hbr.top.filled)))
    np.testing.assert_array_equal(patterns, np.arange(64))
    chosen, few = checked_pairs(hbr, slots[[3, 1]], [63, 0])
    assert chosen.tolist() == slots[[3, 1]].tolist() and few.tolist() == [63, 0]


def test_empty_cells_and_unknown_patterns_are_refused(shipped_hbr):
    hbr, _ = shipped_hbr
    empty = int(np.flatnonzero(~np.asarray(hbr.top.filled))[0])
    with pytest.raises(ValueError, match=rf"skills \[{empty}\] are not filled cells of the top layer"):
        checked_pairs(hbr, [empty], None)
    for bad in ([64], [-1], []):
        with pytest.raises(ValueError, match=r"patterns must be in \[0, 64\)"):
            checked_pairs(hbr, None, bad)


def test_stored_ends_are_the_skills_descriptors_in_metres(shipped_hbr):
    hbr, task = shipped_hbr
    slots = np.flatnonzero(np.asarray(hbr.top.filled))[:5]
    ends = stored_ends(hbr, task, slots)
    assert ends.shape == (5, 3)
    xy = np.asarray(hbr.top.descriptors)[slots] * 2 * task.extent - task.extent
    np.testing.assert_allclose(ends[:, :2], xy, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(ends[:, 2], np.asarray(hbr.top.extras["arrival_yaw"])[slots])
    np.testing.assert_allclose(ends, np.asarray(skill_ends(hbr.top.descriptors[slots], hbr.top.extras["arrival_yaw"][slots],
                                                           task.extent)))
