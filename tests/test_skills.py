"""RTE's model of the skills: repertoire prior, observations, prediction for all actions at once."""

import jax.numpy as jnp
import numpy as np

from hte_jax.hbr.store import load_hbr
from hte_jax.online.gp import add_observation, empty_gp
from hte_jax.online.skills import OUTCOME_DIM, action_set, displacement_of, outcome, predict


def test_prior_is_the_repertoire_and_observations_correct_it():
    hbr, task, _ = load_hbr()
    actions = action_set(hbr.top, task.extent, pad_to=3000)
    filled = int(hbr.top.filled.sum())
    assert actions.size == 3000 and int(actions.mask.sum()) == filled
    model = empty_gp(80, actions.inputs.shape[1], OUTCOME_DIM)
    mean, var = predict(model, actions)
    stored = np.asarray(task.denormalise(hbr.top.descriptors[actions.slots[:filled]]))
    np.testing.assert_allclose(np.asarray(displacement_of(mean))[:filled, :2], stored, atol=1e-5)
    yaw = np.asarray(hbr.top.extras["arrival_yaw"])[np.asarray(actions.slots[:filled])]
    np.testing.assert_allclose(np.asarray(displacement_of(mean))[:filled, 2], yaw, atol=1e-5)
    # the damaged robot did (0.1, 0, 0) instead: that action now predicts it, far actions keep their prior
    index = 5
    model = add_observation(model, actions.inputs[index], outcome(jnp.asarray([0.1, 0.0, 0.0])), actions.prior[index])
    mean, var = predict(model, actions)
    np.testing.assert_allclose(np.asarray(mean[index]), outcome(jnp.asarray([0.1, 0.0, 0.0])), atol=0.1)
    assert float(var[index]) < 0.01 * 0.2
    far = np.argmax(np.linalg.norm(np.asarray(actions.inputs[:filled]) - np.asarray(actions.inputs[index]), axis=1))
    np.testing.assert_allclose(np.asarray(mean[far]), np.asarray(actions.prior[far]), atol=1e-6)
