"""Batched MJX rollouts: standing, walking, damages, invalid individuals (acceptance 2-5).

Every test reuses one module-wide batch of 16 rollouts (one compilation) where it can:
MJX compiles take ~20 s each on a 2-core CPU.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.sim.controller import commanded_travel, servo_command, target_table
from hte_jax.sim.damage import DAMAGED_POSE, damage_mask, make_damage, paper_damage_masks
from hte_jax.sim.robot import RobotConfig, build_spec, load_robot, mj_model, without_idle_springs
from hte_jax.sim.env import InvalidReason, reflex_braced
from hte_jax.sim.rollout import RolloutSpec, initial_state, rollout, standing_state

# Bit for bit: the tilt reflex's held pose and chained rollouts against other compiled paths.
pytestmark = pytest.mark.exact_numerics


def _gait(amplitude, hip, lift):
    """The 36 controller parameters of a gait: per leg (amplitude, phase, duty 0.5) of the hip
    then of the vertical signal, the hip's phase from `hip`, the vertical one's from `lift`."""
    return np.array([[amplitude, h, 0.5, amplitude, v, 0.5] for h, v in zip(hip, lift)], np.float32).reshape(36)


# Tripod gait of the 36-parameter controller, per leg (a, p, d) hip then (a, p, d) vertical.
# Legs 0, 2, 4 lift together, 1, 3, 5 half a period later; the hip swing leads the vertical
# signal by a quarter period, mirrored between the right (0-2) and left (3-5) sides; half
# amplitudes (hip +-pi/16, femur +-pi/8) keep the body within a few degrees of level.
TRIPOD = _gait(0.5, hip=(0.75, 0.25, 0.75, 0.75, 0.25, 0.75), lift=(0.0, 0.5, 0.0, 0.5, 0.0, 0.5))
# A wave gait: leg L lifts at phase L/6, so at most three legs are in the air and the
# robot keeps walking with any one leg (or both middle legs) blocked in the air.
WAVE = _gait(1.0, hip=(0.25, 0.42, 0.58, 0.25, 0.42, 0.58), lift=(0.0, 0.17, 0.33, 0.5, 0.67, 0.83))

SPEC = RolloutSpec(num_steps=300, pose_steps=tuple(range(0, 301, 10)), record_feet=True, record_joints=True,
                   record_joint_travel=True)
STAND, TRIPOD_IDX, DAMAGED, NAN_PARAMS, TIPPING, EXPLODED, NAN_STATE, WAVE_IDX = 0, 1, slice(2, 9), 9, 10, 11, 12, 13
BAD = [NAN_PARAMS, TIPPING, EXPLODED, NAN_STATE]
GOOD = [i for i in range(16) if i not in BAD]


def _batch_inputs(robot):
    damages = np.zeros((16, 6), bool)
    damages[DAMAGED] = paper_damage_masks()
    params = np.random.default_rng(0).uniform(size=(16, 36)).astype(np.float32)
    params[STAND] = 0.0
    params[TRIPOD_IDX] = TRIPOD
    params[DAMAGED] = WAVE
    params[WAVE_IDX] = WAVE
    init = standing_state(robot, jnp.asarray(damages))
    return params, jnp.asarray(damages), init


def _corrupt(params, init):
    """Make individuals 9-12 invalid in four different ways."""
    params = params.copy()
    params[NAN_PARAMS, 3] = np.nan  # NaN commands: the physics goes NaN in the first step
    qpos, qvel = np.array(init.qpos), np.array(init.qvel)
    half = math.radians(40) / 2  # rolled by 40 degrees, 0.3 m up, spinning over at 6 rad/s
    qpos[TIPPING, 2:7] = [0.3, math.cos(half), math.sin(half), 0.0, 0.0]
    qvel[TIPPING, 3] = 6.0
    qvel[EXPLODED, 6:] = 500.0
    qvel[NAN_STATE, 0] = np.nan
    return params, init.replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))


@pytest.fixture(scope="module")
def batch(robot):
    params, damages, init = _batch_inputs(robot)
    bad_params, bad_init = _corrupt(params, init)
    dirty = rollout(robot, jnp.asarray(bad_params), damages, bad_init, SPEC)
    clean = rollout(robot, jnp.asarray(params), damages, init, SPEC)
    return {"params": params, "damages": np.asarray(damages), "init": init, "dirty": dirty, "clean": clean}


def _np(x):
    return np.asarray(x)


def _up_z(quat):
    return 1.0 - 2.0 * (quat[..., 1] ** 2 + quat[..., 2] ** 2)


@pytest.mark.slow
def test_standing_state(robot):
    state = standing_state(robot)
    assert state.qpos.shape == (25,)
    assert float(state.qpos[2]) == pytest.approx(0.134, abs=0.003)
    assert float(jnp.abs(state.qpos[:2]).max()) == 0.0
    assert float(jnp.abs(state.qvel).max()) < 0.05


def test_standing_state_under_a_callers_jit_equals_its_eager_run(robot):
    """A traced damage mask (standing_state inside a caller's jit, as the skill renderer calls it) settles the
    robots as a concrete one does, to float32 rounding (one program against three)."""
    damages = np.asarray(paper_damage_masks()[:2])
    eager = standing_state(robot, damages)
    traced = jax.jit(lambda d: standing_state(robot, d))(jnp.asarray(damages))
    assert eager.qpos.shape == traced.qpos.shape == (2, 25)
    np.testing.assert_allclose(np.asarray(traced.qpos), np.asarray(eager.qpos), atol=1e-5)  # one program vs three: float32 rounding


def test_initial_state_places_damaged_legs():
    robot = load_robot()
    state = initial_state(robot, jnp.asarray([False, False, True, False, False, False]))
    np.testing.assert_allclose(_np(state.qpos[13:16]), DAMAGED_POSE, atol=1e-6)
    assert np.all(_np(state.qpos[7:13]) == 0)


@pytest.mark.slow
def test_zero_parameters_stand_still(batch):
    """Acceptance 2: steady base height, drift < 1 cm over 3 s."""
    res = batch["clean"]
    pos = _np(res.base_pos[STAND])
    assert bool(res.valid[STAND])
    assert np.ptp(pos[:, 2]) < 0.002
    assert np.linalg.norm(pos[-1, :2] - pos[0, :2]) < 0.01
    assert _up_z(_np(res.base_quat[STAND])).min() > math.cos(math.radians(2))


@pytest.mark.slow
def test_tripod_walks_forward_upright(batch):
    """Acceptance 3: > 0.2 m forward in 3 s, body upright throughout."""
    res = batch["clean"]
    pos = _np(res.base_pos[TRIPOD_IDX])
    assert bool(res.valid[TRIPOD_IDX])
    assert pos[-1, 0] - pos[0, 0] > 0.2
    assert abs(pos[-1, 1] - pos[0, 1]) < 0.1
    assert _up_z(_np(res.base_quat[TRIPOD_IDX])).min() > math.cos(math.radians(10))
    contacts = _np(res.foot_contacts[TRIPOD_IDX])
    assert 0.2 < contacts.mean() < 0.9  # feet alternate between stance and swing


@pytest.mark.slow
def test_damaged_feet_never_touch_the_floor(batch):
    """Acceptance 4: the 7 paper conditions in one batch; blocked legs stay in the air."""
    res, masks = batch["clean"], batch["damages"][DAMAGED]
    assert masks.shape == (7, 6)
    assert _np(res.valid[DAMAGED]).all()
    contacts = _np(res.foot_contacts[DAMAGED])  # (7, 300, 6)
    foot_z = _np(res.foot_pos[DAMAGED])[..., 2]
    for k, mask in enumerate(masks):
        assert not contacts[k][:, mask].any()
        assert foot_z[k][:, mask].min() > 0.1
        assert contacts[k][:, ~mask].any(axis=0).all()  # every healthy leg does touch
        pos = _np(res.base_pos[DAMAGED][k])
        assert np.linalg.norm(pos[-1, :2] - pos[0, :2]) > 0.05  # it still walks


@pytest.mark.slow
def test_joint_travel_sums_the_joint_angle_changes(batch, robot):
    """The travel equals sum |q(t+1) - q(t)| of the recorded angles; damaged legs hardly move."""
    res, masks = batch["clean"], batch["damages"]
    joints = np.concatenate([_np(res.joint_pos), _np(res.final_state.qpos)[:, None, 7:]], axis=1)  # (B, T+1, 18)
    expected = np.abs(np.diff(joints.astype(np.float64), axis=1)).sum(axis=1)
    np.testing.assert_allclose(_np(res.joint_travel), expected, rtol=1e-4, atol=1e-4)
    legs = _np(res.joint_travel)[DAMAGED].reshape(7, 6, 3).sum(-1)
    damaged = masks[DAMAGED]
    assert legs[damaged].max() < 0.1 * legs[~damaged].min()
    dirty = _np(batch["dirty"].joint_travel)
    assert np.isfinite(dirty).all()  # a blown-up individual adds nothing after it went invalid


def _period_travel(params):
    """(B, 36) controllers -> (B, 18) rad each joint's target moves around one period (NumPy)."""
    tables = np.stack([_np(target_table(jnp.asarray(p))) for p in params]).astype(np.float64)
    return np.abs(np.roll(tables, -1, axis=1) - tables).sum(axis=1)


@pytest.mark.slow
def test_target_travel_is_what_the_controller_commanded_whatever_the_damage(batch):
    """Without the reflex, 3 s of one controller command three periods of its target travel
    (`commanded_travel`, per leg), on a damaged leg too: the damage holds the leg, it does not change
    what the controller asks (a locked leg must still look stuck)."""
    res, params = batch["clean"], batch["params"]
    valid = _np(res.valid)
    assert valid[DAMAGED].all() and valid.sum() >= 12
    np.testing.assert_allclose(_np(res.target_travel)[valid], 3 * _period_travel(params[valid]), rtol=1e-4, atol=1e-4)
    legs = _np(res.target_travel).reshape(-1, 6, 3).sum(-1)
    np.testing.assert_allclose(legs[valid], 3 * _np(commanded_travel(jnp.asarray(params[valid]))), rtol=1e-4)
    assert (legs[DAMAGED][batch["damages"][DAMAGED]] > 1.0).all()  # the held legs were asked to move


@pytest.mark.slow
def test_invalid_rollouts_are_flagged_and_isolated(batch):
    """Acceptance 5: NaN, explosion, flip are flagged per individual; the batch survives."""
    dirty, clean = batch["dirty"], batch["clean"]
    valid = _np(dirty.valid)
    reason = _np(dirty.invalid_reason)
    step = _np(dirty.invalid_step)
    assert not valid[BAD].any()
    assert reason[NAN_PARAMS] & InvalidReason.NON_FINITE and step[NAN_PARAMS] == 0
    assert reason[TIPPING] & InvalidReason.FLIPPED and 1 <= step[TIPPING] < 20
    assert reason[EXPLODED] & InvalidReason.EXPLODED and step[EXPLODED] == 0
    assert reason[NAN_STATE] & InvalidReason.NON_FINITE and step[NAN_STATE] == 0
    assert np.all(step[valid] == SPEC.num_steps) and np.all(reason[valid] == 0)
    # Blown-up individuals are frozen at their last valid state: no NaN leaks out ...
    for i in (NAN_PARAMS, TIPPING, EXPLODED):
        for leaf in jax.tree.leaves(jax.tree.map(lambda x: x[i], dirty)):
            assert np.isfinite(_np(leaf).astype(float)).all()
    # ... and the other individuals are exactly what they are in a batch without them.
    for a, b in zip(jax.tree.leaves(dirty), jax.tree.leaves(clean)):
        np.testing.assert_array_equal(_np(a)[GOOD], _np(b)[GOOD])


@pytest.mark.slow
def test_controller_segments_reset_the_clock(robot, batch):
    """(B, S, 36): three identical 1 s segments equal one 3 s controller; a zero segment stops."""
    init = jax.tree.map(lambda x: x[TRIPOD_IDX], batch["init"])
    params = jnp.asarray(np.stack([np.stack([TRIPOD] * 3), np.stack([TRIPOD, 0 * TRIPOD, 0 * TRIPOD])]))
    res = rollout(robot, params, jnp.zeros(6, bool), init, SPEC)
    np.testing.assert_allclose(_np(res.base_pos[0]), _np(batch["clean"].base_pos[TRIPOD_IDX]), atol=1e-5)
    pos = _np(res.base_pos[1])
    assert pos[10, 0] - pos[0, 0] > 0.05  # walked during the first second
    assert np.linalg.norm(pos[-1, :2] - pos[15, :2]) < 0.01  # then stood still


@pytest.mark.slow
def test_reset_free_chaining(robot, batch):
    """Two chained 1.5 s rollouts from arbitrary states equal one 3 s rollout."""
    idx = [TRIPOD_IDX, WAVE_IDX]
    init = jax.tree.map(lambda x: x[jnp.asarray(idx)], batch["init"])
    half = RolloutSpec(num_steps=150, pose_steps=(150,))
    params = jnp.asarray(batch["params"][idx])
    first = rollout(robot, params, jnp.zeros(6, bool), init, half)
    # the second half starts at control step 150, i.e. at phase 50 of the 1 s period
    signals = params.reshape(2, 12, 3)
    shifted = signals.at[:, :, 1].set((signals[:, :, 1] + 0.5) % 1.0).reshape(2, 36)
    second = rollout(robot, shifted, jnp.zeros(6, bool), first.final_state, half)
    full = batch["clean"]
    np.testing.assert_allclose(_np(first.base_pos[:, 0]), _np(full.base_pos[jnp.asarray(idx), 15]), atol=1e-5)
    np.testing.assert_allclose(_np(second.base_pos[:, 0]), _np(full.base_pos[jnp.asarray(idx), 30]), atol=2e-3)


@pytest.mark.slow
def test_mjx_agrees_with_native_mujoco(robot, batch):
    """The tripod in native MuJoCo (float64, same servo law) ends within 3 cm of MJX."""
    model = mj_model(robot.config)
    data = mujoco.MjData(model)
    state = jax.tree.map(lambda x: np.asarray(x[TRIPOD_IDX], np.float64), batch["init"])
    data.qpos[:], data.qvel[:] = state.qpos, state.qvel
    table = _np(target_table(jnp.asarray(TRIPOD)))
    for k in range(300):
        data.ctrl[:] = _np(servo_command(jnp.asarray(table[k % 100]), jnp.asarray(data.qpos[7:]), 5.0))
        mujoco.mj_step(model, data)
    mjx_final = _np(batch["clean"].base_pos[TRIPOD_IDX, -1])
    np.testing.assert_allclose(data.qpos[:2], mjx_final[:2], atol=0.03)


def test_bad_inputs_are_clear_errors(robot):
    init = initial_state(robot)
    with pytest.raises(ConfigError, match="params must have shape"):
        rollout(robot, jnp.zeros((2, 35)), jnp.zeros(6, bool), init, SPEC)
    with pytest.raises(ConfigError, match="damage must have shape"):
        rollout(robot, jnp.zeros((2, 36)), jnp.zeros(5, bool), init, SPEC)
    with pytest.raises(ConfigError, match="do not divide"):
        rollout(robot, jnp.zeros((2, 7, 36)), jnp.zeros(6, bool), init, SPEC)
    with pytest.raises(ConfigError, match="pose step"):
        RolloutSpec(num_steps=10, pose_steps=(11,))
    with pytest.raises(ConfigError, match="num_steps"):
        RolloutSpec(num_steps=0)


def _tilted(state, degrees: float, lift: float):
    """Batched `state` rolled by `degrees` about the body's x axis and lifted by `lift` metres."""
    half = math.radians(degrees) / 2
    qpos = np.array(state.qpos)
    qpos[:, 2] += lift
    qpos[:, 3:7] = [math.cos(half), math.sin(half), 0.0, 0.0]
    return state.replace(qpos=jnp.asarray(qpos))


@pytest.mark.slow
def test_tilt_reflex_holds_the_neutral_pose_until_the_segment_ends(robot, batch):
    """RobotConfig.reflex_tilt: a robot started 15 degrees tilted drops its gait for the neutral pose
    for the rest of the 1 s segment, then walks the next segment; an upright tripod never fires it.
    Reference: the same physics without the reflex, running the all-zero controller where it fired."""
    reflexive = load_robot(dataclasses.replace(robot.config, reflex_tilt=0.1))
    upright = jax.tree.map(lambda x: x[jnp.asarray([TRIPOD_IDX, TRIPOD_IDX])], batch["init"])
    starts = jax.tree.map(lambda a, b: jnp.stack([a[0], b[1]]), _tilted(upright, 15.0, 0.05), upright)
    spec = RolloutSpec(num_steps=200, pose_steps=(0, 50, 100, 200), record_joint_travel=True)
    tripods = jnp.asarray(np.stack([np.stack([TRIPOD, TRIPOD])] * 2))
    reflexes = rollout(reflexive, tripods, jnp.zeros(6, bool), starts, spec)
    reference = rollout(robot, tripods.at[0, 0].set(0.0), jnp.zeros(6, bool), starts, spec)
    assert _np(reflexes.valid).all()
    np.testing.assert_allclose(_np(reflexes.base_pos), _np(reference.base_pos), atol=1e-5)
    np.testing.assert_allclose(_np(reflexes.final_state.qpos), _np(reference.final_state.qpos), atol=1e-4)
    pos = _np(reflexes.base_pos[0])
    assert np.linalg.norm(pos[2, :2] - pos[1, :2]) < 0.01  # stood in its first second
    assert pos[3, 0] - pos[2, 0] > 0.03  # and walked in the second
    assert _up_z(_np(reflexes.base_quat[1])).min() > math.cos(0.1)  # the upright tripod stayed below the angle
    # the gait's commanded travel: none while the reflex held the tilted tripod, then one period; the upright
    # tripod's two periods
    period = _period_travel(TRIPOD[None])[0]
    np.testing.assert_allclose(_np(reflexes.target_travel), [period, 2 * period], rtol=1e-4, atol=1e-4)
    # without the reflex, the tilted tripod does not stand still in its first second
    free = rollout(robot, tripods, jnp.zeros(6, bool), starts, spec)
    assert np.abs(_np(free.base_pos[0, 2]) - pos[2]).max() > 0.01
    # reflex_release: once back below 0.05 rad the gait resumes within the same second
    releasing = load_robot(dataclasses.replace(robot.config, reflex_tilt=0.1, reflex_release=0.05))
    released = rollout(releasing, tripods, jnp.zeros(6, bool), starts, spec)
    assert _np(released.valid).all()
    np.testing.assert_array_equal(_np(released.base_pos[1]), _np(reflexes.base_pos[1]))  # never fired
    walked = _np(released.base_pos[0])
    assert walked[2, 0] - walked[1, 0] > 0.01 > np.linalg.norm(pos[2, :2] - pos[1, :2])


def test_reflex_braced_matches_a_numpy_reference():
    """rollout.reflex_braced (angle, release) on random tilted states, batched in jax and one at a
    time in NumPy, against the rule written with angles: tilt = arccos(up_z)."""
    model = mj_model(RobotConfig())
    rng = np.random.default_rng(3)
    n = 400
    quat = rng.normal(size=(n, 4)) * [1.0, 0.3, 0.3, 1.0]
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    qpos = np.zeros((n, model.nq))
    qpos[:, 3:7] = quat
    braced, fresh = rng.random(n) < 0.5, rng.random(n) < 0.3
    tilt = np.arccos(np.clip(1.0 - 2.0 * (quat[:, 1] ** 2 + quat[:, 2] ** 2), -1, 1))
    for tilt_at, release in [(0.3, 0.0), (0.3, 0.15), (0.4, 0.0), (0.3, 0.2)]:
        config = RobotConfig(reflex_tilt=tilt_at, reflex_release=release)
        held = braced & ~fresh & ((release == 0.0) | (tilt > release))
        expected = held | (tilt > tilt_at)
        got = jax.vmap(lambda b, f, q: reflex_braced(b, f, q, config))(
            jnp.asarray(braced), jnp.asarray(fresh), jnp.asarray(qpos, jnp.float32))
        away = (np.abs(tilt - tilt_at) > 1e-3) & (np.abs(tilt - release) > 1e-3)
        assert away.sum() > n // 2 and 0 < expected[away].sum() < away.sum()
        np.testing.assert_array_equal(np.asarray(got)[away], expected[away])
        one = [bool(reflex_braced(np.bool_(b), np.bool_(f), q, config)) for b, f, q in zip(braced, fresh, qpos)]
        np.testing.assert_array_equal(np.asarray(one)[away], expected[away])


def test_reflex_tilt_is_validated():
    with pytest.raises(ConfigError, match="reflex_tilt"):
        RobotConfig(reflex_tilt=-0.1)
    with pytest.raises(ConfigError, match="must be below reflex_tilt"):
        RobotConfig(reflex_tilt=0.3, reflex_release=0.3)
    with pytest.raises(ConfigError, match="set reflex_tilt > 0"):
        RobotConfig(reflex_release=0.1)


def test_spring_term_is_off_only_where_it_changes_no_force():
    """`mj_model` switches MuJoCo's spring term off for a model without springs (it kept XLA from
    compiling a rollout spread over several devices with jax 0.11): the hexapod's native steps
    are bit-identical with the term on and off; a model with a joint spring keeps it."""
    model = mj_model(RobotConfig())
    assert model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_SPRING
    with_term = build_spec(RobotConfig()).compile()  # a fresh model (mj_model's is cached): the term on
    assert not with_term.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_SPRING
    runs = []
    for m in (model, with_term):
        data = mujoco.MjData(m)
        data.qpos[2] = 0.2
        data.ctrl[:] = np.sin(np.arange(m.nu))
        for _ in range(200):
            mujoco.mj_step(m, data)
        runs.append(data.qpos.copy())
    np.testing.assert_array_equal(runs[0], runs[1])
    assert np.abs(runs[0][:3] - [0.0, 0.0, 0.2]).max() > 0.01  # the robot did move
    sprung = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint type='hinge' stiffness='2'/><geom size='0.1'/></body></worldbody></mujoco>")
    assert not without_idle_springs(sprung).opt.disableflags & mujoco.mjtDisableBit.mjDSBL_SPRING


@pytest.mark.slow
def test_raised_and_locked_damages_give_the_leg_mask_bits():
    """One program of `Damage` inputs runs both models (the model is data) and gives each mask program's bits
    (every program at the same batch: rows 0-2 raised, 3-5 locked)."""
    params = jnp.tile(jax.random.uniform(jax.random.key(4), (3, 36)), (2, 1))
    masks = np.tile(np.stack([damage_mask(()), damage_mask((1,)), damage_mask((1, 4))]), (2, 1))
    spec = RolloutSpec(num_steps=100, pose_steps=(0, 100))
    models = ("raised", "locked")
    robots = [load_robot(dataclasses.replace(load_robot().config, damage_model=model)) for model in models]
    starts = [standing_state(robot, masks) for robot in robots]
    by_mask = [rollout(robot, params, masks, start, spec) for robot, start in zip(robots, starts)]
    rows = [slice(0, 3), slice(3, 6)]  # each model's rows
    damage = jax.tree.map(lambda *x: jnp.concatenate(x), *[make_damage(masks[r], m) for r, m in zip(rows, models)])
    start = jax.tree.map(lambda *x: jnp.concatenate(x), *[jax.tree.map(lambda a: a[r], s) for r, s in zip(rows, starts)])
    by_part = rollout(robots[0], params, damage, start, spec)
    for name in ("base_pos", "foot_contacts", "invalid_reason"):
        for r, result in zip(rows, by_mask):
            np.testing.assert_array_equal(np.asarray(getattr(result, name))[r], np.asarray(getattr(by_part, name))[r])
