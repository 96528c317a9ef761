"""The flip proxy's bookkeeping (benchmarks/flip_proxy.py): first invalid phase and altered robots."""

import numpy as np
import pytest

from hte_jax.sim.robot import FLOOR_BIT, RobotConfig, mj_model
from tests.benchmark_runner import benchmark_module

flip_proxy = benchmark_module("flip_proxy")


def test_first_invalid_phase_is_the_earliest_bad_phase():
    # robots: valid throughout; bad in step 2 (and later); bad only in the neutral second; bad in step 1
    reasons = np.array([[0, 0, 0, 4],
                        [0, 1, 0, 0],
                        [0, 2, 0, 1]])
    rest_valid = np.array([True, False, False, True])
    phase = flip_proxy.first_invalid_phase(reasons, rest_valid)
    np.testing.assert_array_equal(phase, [-1, 1, 3, 0])
    assert [flip_proxy.PHASES[p] for p in phase[1:]] == ["step 2", "neutral", "step 1"]


def test_altered_robot_lightens_and_unfloors_only_the_named_legs():
    config = RobotConfig(body_floor_contact=True)
    base = mj_model(config)
    robot = flip_proxy.altered_robot(config, [2], lighter=1e-3, touchless=True)
    model = robot.model
    for part in (1, 2, 3):
        leg2, leg3 = base.body(f"leg_2_{part}").id, base.body(f"leg_3_{part}").id
        np.testing.assert_allclose(np.asarray(model.body_mass)[leg2], 1e-3 * base.body_mass[leg2], rtol=1e-6)
        np.testing.assert_allclose(np.asarray(model.body_mass)[leg3], base.body_mass[leg3])
    contype = np.asarray(model.geom_contype)
    for name in ("leg_2_1", "leg_2_2", "leg_2_3", "foot_2"):
        assert contype[base.geom(name).id] & FLOOR_BIT == 0
    for name in ("leg_3_3", "foot_3", "base_link"):
        assert contype[base.geom(name).id] & FLOOR_BIT
    assert base.body_mass[base.body("leg_2_2").id] > 0.1  # the cached model is untouched


def test_skill_miss_median_pools_the_whole_skills_of_every_action():
    misses = [np.array([0.1, 0.3]), np.array([], np.float32), np.array([0.2])]
    assert flip_proxy.skill_miss_median(misses) == pytest.approx(0.2)
    assert np.isnan(flip_proxy.skill_miss_median([np.array([])]))
    assert np.isnan(flip_proxy.skill_miss_median([]))


def test_reflex_specs_parse_into_robot_options():
    assert flip_proxy.parse_reflex("0.3") == (0.3, 0.0, 0.0)
    assert flip_proxy.reflex_options(flip_proxy.parse_reflex("0.3/0.15/1")) == {
        "reflex_tilt": 0.3, "reflex_release": 0.15, "reflex_rate": 1.0}
    with pytest.raises(ValueError, match="TILT"):
        flip_proxy.parse_reflex("0.3/0.1/1/2")
    with pytest.raises(SystemExit):
        flip_proxy.main(["--reflex-tilt", "0.3/0.4"])  # release above the angle: a parser error (exit 2)
