"""APROL's 21 damaged repertoires (issue 5): each is trained under its own damage, and its elites
re-simulate under that damage and not under another (a separate module from test_flat.py so that
pytest-xdist can run the two side by side)."""

import json

import jax
import jax.numpy as jnp
import matplotlib.image
import numpy as np
import pytest

from experiments.train_flat import main as flat_main
from hte_jax.flat.store import load_flat
from hte_jax.flat.task import evaluate_flat
from hte_jax.flat.training import preset
from hte_jax.sim import standing_state
from hte_jax.sim.damage import APROL_DAMAGES

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def aprol_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("flat") / "aprol"
    assert flat_main(["--variant", "aprol", "--preset", "tiny", "--out", str(out), "--no-progress"]) == 0
    return out



def test_aprol_repertoires_are_each_trained_under_their_own_damage(aprol_run, robot):
    flat, meta = load_flat(aprol_run / "repertoires.npz")
    assert flat.damages == tuple(APROL_DAMAGES) and len(flat) == 21
    summary = json.loads((aprol_run / "summary.json").read_text())
    config = preset("tiny", "aprol")
    assert summary["evaluations"] == 21 * (config.init_size + config.generations * config.batch_size)
    masks = flat.damage_masks
    for r, name in enumerate(flat.damages):
        rep = flat[r]
        filled = np.asarray(rep.filled)
        assert filled.sum() == summary["elites"][name] > 0
        fraction = np.asarray(rep.extras["contact_fraction"])[filled]
        # the damaged legs are blocked in the air: never on the ground in any elite of that repertoire
        assert (fraction[:, masks[r]] == 0).all(), name
        assert (fraction[:, ~masks[r]] > 0).any(), name
    # re-simulating elites under their own damage reproduces them; under another damage it does not
    task = flat.task
    evaluate = jax.jit(lambda start, mask, genes: evaluate_flat(robot, task, start, mask, None, genes))
    for r in (0, 6, 20):
        rep = flat[r]
        # 4 elites (the first ones, repeated where fewer are filled): every call one compiled program
        rows = np.resize(np.flatnonzero(np.asarray(rep.filled)), 4)
        genes = rep.genotypes[rows]
        own = evaluate(standing_state(robot, masks[r]), jnp.asarray(masks[r]), genes)
        np.testing.assert_allclose(np.asarray(own.descriptors), np.asarray(rep.descriptors[rows]), atol=1e-4)
        np.testing.assert_allclose(np.asarray(own.extras["arrival_yaw"]), np.asarray(rep.extras["arrival_yaw"][rows]),
                                   atol=1e-4)
        # the ideal arc's heading, 2 atan2(y, x), amplifies last-bit differences of cm-sized moves
        np.testing.assert_allclose(np.asarray(own.fitnesses), np.asarray(rep.fitnesses[rows]), atol=1e-2)
        other = (r + 7) % 21
        moved = evaluate(standing_state(robot, masks[other]), jnp.asarray(masks[other]), genes)
        assert np.abs(np.asarray(moved.extras["contact_fraction"]) - np.asarray(rep.extras["contact_fraction"][rows])).max() > 0.05
    image = matplotlib.image.imread(aprol_run / "plots" / "xy_fitness_per_damage.png")
    assert image.shape[0] > 200 and image.std() > 0
