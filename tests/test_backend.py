"""MJX's implementation as a setting (`RobotConfig.impl`, issue 38): every CLI takes it, runs store it
and resume with it (runs from before it: "jax"), asking for "warp" without the warp extra is a
one-line error, and where the extra is installed MuJoCo Warp runs the project's rollout on the CPU
as MJX's JAX implementation does (the tests that need it skip otherwise)."""

import ctypes
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.maze_eval import main as maze_main
from experiments.train_flat import main as flat_main
from experiments.train_hbr import main as hbr_main
from hte_jax.errors import ConfigError
from hte_jax.flat.training import normalised_config as flat_normalised
from hte_jax.flat.training import preset as flat_preset
from hte_jax.geometry import planar_pose
from hte_jax.hbr.training import PRESETS, normalised_config
from hte_jax.qd.io import prepare_run_dir, read_checkpoint
from hte_jax.sim.damage import edited_model, paper_damage_masks, parse_damages
from hte_jax.sim.mjx_import import mjx, require_impl, warp_installed
from hte_jax.sim.robot import FOOT_RADIUS, RobotConfig, load_robot, mj_model
from hte_jax.sim.env import InvalidReason
from hte_jax.sim.rollout import RolloutSpec, empty_data, initial_state, rollout, standing_state
from tests.commands_script import near_goal_maze
from tests.processes import cpu_devices_env

ROOT = Path(__file__).resolve().parents[1]
needs_warp = pytest.mark.skipif(not warp_installed(), reason="MJX's Warp backend is not installed "
                                                             "(warp-lang missing: pip install -e '.[warp]')")


def _shown(main, args, capsys) -> dict:
    assert main([*args, "--show-config"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("kind", ["hbr", "flat", "maze"])
def test_impl_is_a_setting_of_every_cli_stored_and_resumed(kind, tmp_path, capsys):
    """--impl and --set solver.impl reach the configuration a run stores; a resumed run keeps the
    stored backend (a folder from before the setting: jax), and another one is refused."""
    main, args, base = {
        "hbr": (hbr_main, ["--preset", "tiny"], PRESETS["tiny"].to_dict()),
        "flat": (flat_main, ["--preset", "tiny", "--variant", "2d"], flat_preset("tiny", "2d").to_dict()),
        "maze": (maze_main, [], None),
    }[kind]
    assert _shown(main, args, capsys)["impl"] == "jax"
    assert _shown(main, [*args, "--impl", "warp"], capsys)["impl"] == "warp"
    assert _shown(main, [*args, "--set", "solver.impl=warp"], capsys)["impl"] == "warp"
    assert main([*args, "--impl", "cuda", "--show-config"]) == 2
    assert "impl must be one of ('jax', 'warp')" in capsys.readouterr().err
    if base is None:  # maze_eval does not resume
        return
    normalise = normalised_config if kind == "hbr" else flat_normalised
    args = [*args, "--out", str(tmp_path)]
    (tmp_path / "config.json").write_text(json.dumps({k: v for k, v in base.items() if k != "impl"}))
    assert _shown(main, [*args, "--resume"], capsys) == base  # stored before the setting: jax
    (tmp_path / "config.json").write_text(json.dumps({**base, "impl": "warp"}))
    resumed = _shown(main, [*args, "--resume"], capsys)
    assert resumed == {**base, "impl": "warp"}
    assert prepare_run_dir(tmp_path, resumed, True, normalise=normalise) == tmp_path
    explicit = _shown(main, [*args, "--resume", "--impl", "jax"], capsys)
    with pytest.raises(ConfigError, match="differs in: impl"):
        prepare_run_dir(tmp_path, explicit, True, normalise=normalise)


MISSING_EXTRA = """
import sys
sys.modules["warp"] = None  # warp-lang cannot be imported, whatever this machine has installed
from experiments.maze_eval import main as maze
from experiments.train_flat import main as flat
from experiments.train_hbr import main as hbr
from experiments.train_spare import main as spare
out = sys.argv[1]
print([flat(["--variant", "2d", "--preset", "tiny", "--impl", "warp", "--out", out + "/flat"]),
       hbr(["--preset", "tiny", "--set", "solver.impl=warp", "--out", out + "/hbr"]),
       spare(["--impl", "warp", "--out", out + "/spare", "--no-progress"]),
       maze(["--impl", "warp", "--variant", "rte", "--damage", "none", "--out", out + "/maze", "--no-progress"])])
"""


@pytest.mark.slow
def test_asking_for_warp_without_the_extra_is_a_one_line_error(tmp_path, xla_defaults):
    """In a process where warp-lang does not import, every CLI asked for impl=warp exits 2 with one
    line naming the extra, and the training CLIs write no run folder. The process compiles at XLA's
    defaults (`xla_defaults`): train_spare loads the shipped HBR first, 4 s there against ~45 s in the
    fast code generation."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-c", MISSING_EXTRA, str(tmp_path)], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=900)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "[2, 2, 2, 2]"
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 4, proc.stderr
    for line in lines:
        assert line.startswith("error: impl='warp' needs MJX's Warp backend") and 'pip install -e ".[warp]"' in line
    assert not any((tmp_path / name).exists() for name in ("flat", "hbr", "spare"))


# 3 s from the standing state, intact and under the paper's damages, the tilt reflex armed.
AGREEMENT_SPEC = RolloutSpec(num_steps=300, pose_steps=(300,), record_feet=True)


def _run(impl: str, params, damages):
    """Standing state, final planar pose, validity and deepest foot penetration under MJX's `impl`."""
    robot = load_robot(RobotConfig(impl=impl, reflex_tilt=0.3))
    start = standing_state(robot, damages)
    result = rollout(robot, params, damages, start, AGREEMENT_SPEC)
    pose = np.asarray(planar_pose(result.base_pos[:, -1], result.base_quat[:, -1]))
    depth = FOOT_RADIUS - np.asarray(result.foot_pos)[..., 2].min(axis=(1, 2))
    return np.asarray(start.qpos), pose, np.asarray(result.valid), depth


@pytest.mark.slow
@needs_warp
def test_warp_rollouts_agree_with_jax():
    """16 random controllers, half intact, half under the paper's damages, with the tilt reflex armed
    (servo law, damages and reflex act on ctrl / qpos around `mjx.step`): standing states, validity,
    final positions and foot penetration agree within what was measured on the CPU (docs/design.md:
    standing qpos within 3e-6, final position median 0, p90 ~1 mm, max ~3 mm over 32 rollouts)."""
    params = jnp.asarray(np.random.default_rng(7).uniform(size=(16, 36)), jnp.float32)
    damages = jnp.asarray(np.concatenate([np.zeros((8, 6), bool), paper_damage_masks()[np.arange(8) % 7]]))
    (start, pose, valid, depth), (ref_start, ref_pose, ref_valid, ref_depth) = (
        _run(impl, params, damages) for impl in ("warp", "jax"))
    np.testing.assert_allclose(start, ref_start, atol=1e-4)
    assert (valid == ref_valid).sum() >= 15 and valid.sum() >= 12
    both = valid & ref_valid
    error = np.linalg.norm(pose[both, :2] - ref_pose[both, :2], axis=1)
    assert np.median(error) <= 0.002 and np.percentile(error, 90) <= 0.01, error
    assert abs(depth[both].max() - ref_depth[both].max()) <= 0.001


# Every damage model, and a slippery floor, in one batch: model values edited per robot.
EVERY_DAMAGE = "none,leg0:removed,leg2:shortened=0.5,leg3:weak=0.5,leg1:locked,leg4:raised,none:friction=0.25"


def _damage_batch(spelling: str):
    damages = parse_damages(spelling)
    return jax.tree.map(lambda *rows: jnp.stack(rows), *damages.values())


@pytest.mark.slow
@needs_warp
def test_warp_takes_model_edits_per_robot():
    """A `Damage` batch that edits model values (removed, shortened, weak, floor friction) runs under Warp as
    under JAX: each robot's contacts carry its own floor friction and a removed foot has none (Warp reads the
    batched model fields per world), and the settled standing states of every damage model agree with JAX's
    (no sliding: within 1e-4), the removed and shortened legs' stance differing from the intact one in both."""
    damage = _damage_batch(EVERY_DAMAGE)
    robot = load_robot(RobotConfig(impl="warp"))
    data = empty_data(robot, 3)
    lowered = initial_state(robot).qpos.at[2].set(0.12)  # every foot on the floor

    def contacts(one):
        return mjx.forward(edited_model(robot.model, one, robot.info), data.replace(qpos=lowered))

    three = jax.tree.map(lambda x: x[np.array([0, 1, 6])], damage)  # intact, leg 0 removed, friction x 0.25
    found = jax.jit(jax.vmap(contacts))(three)._impl
    count = int(np.asarray(found.nacon).ravel()[0])
    world, geoms = np.asarray(found.contact__worldid)[:count], np.asarray(found.contact__geom)[:count]
    friction = np.asarray(found.contact__friction)[:count, 0]
    feet = set(robot.info.foot_geoms)
    touching = [{int(g) for g in geoms[world == w].ravel()} & feet for w in range(3)]
    assert touching[0] == touching[2] == feet and touching[1] == feet - {robot.info.foot_geoms[0]}
    np.testing.assert_allclose(friction[world == 2], 0.25 * friction[world == 0][: (world == 2).sum()], rtol=1e-6)

    standing = {impl: np.asarray(standing_state(load_robot(RobotConfig(impl=impl)), damage).qpos)
                for impl in ("warp", "jax")}
    np.testing.assert_allclose(standing["warp"], standing["jax"], atol=1e-4)
    for qpos in standing.values():
        moved = np.abs(qpos - qpos[0]).max(axis=1)  # against the intact robot's (measured: 9e-3 and 1.3e-2)
        assert moved[1] > 1e-3 and moved[2] > 1e-3, moved


@pytest.mark.slow
@needs_warp
@pytest.mark.parametrize("devices", [1, 2])
def test_maze_eval_runs_model_editing_damages_under_warp(devices, tmp_path):
    """`maze_eval --impl warp` with damages that edit the model (a removed leg, a slippery floor), in this
    process and on 2 forced CPU devices: one RTE episode per damage in a maze whose goal holds the start,
    each ends after its first valid action, and the run's configuration, records and batch file name the
    backend and the damages."""
    maze = tmp_path / "maze.json"
    maze.write_text(json.dumps(near_goal_maze()))
    damages = "leg0:removed,none:friction=0.5"
    out = tmp_path / "run"
    args = ["--impl", "warp", "--variant", "rte", "--damage", damages, "--replicates", "1", "--max-actions", "2",
            "--iterations", "10", "--roots", "1", "--depth", "3", "--candidates", "10", "--maze", str(maze),
            "--no-progress", "--out", str(out)]
    if devices == 1:
        assert maze_main(args) == 0
    else:
        proc = subprocess.run([sys.executable, "-m", "experiments.maze_eval", *args, "--devices", "2"], cwd=ROOT,
                              env=cpu_devices_env(2), capture_output=True, text=True, timeout=900)
        assert proc.returncode == 0, proc.stderr[-3000:]
    config = json.loads((out / "config.json").read_text())
    assert config["impl"] == "warp" and config["damages"] == damages
    records = json.loads((out / "episodes.json").read_text())["episodes"]
    assert [r["damage"] for r in records] == damages.split(",")
    assert all(r["reached"] and r["actions_taken"] >= 1 for r in records)
    arrays, header = read_checkpoint(out / "episodes_0.npz")
    assert header["metadata"]["damage_models"] == ["removed", "raised"]
    np.testing.assert_array_equal(arrays["damage_friction"], np.float32([1.0, 0.5]))


def _flushed_output(capfd) -> str:
    """What native code and Python wrote to stdout / stderr so far (C stdio buffers flushed first)."""
    ctypes.CDLL(None).fflush(None)
    captured = capfd.readouterr()
    return captured.out + captured.err


@pytest.mark.slow
@needs_warp
def test_warp_is_quiet_at_its_iteration_cap_and_flags_lost_contacts(capfd):
    """MuJoCo Warp's per-step "solver iterations limit reached" is off (it prints without the
    project's model change, and the cap does bind); a vmap around `rollout` shares one call's contact
    buffer among more robots than it was sized for: those rollouts are invalid (WARP_OVERFLOW), and
    Warp's overflow notice stays on."""
    config = RobotConfig(impl="warp")
    robot = load_robot(config)
    ctrl = jnp.asarray(np.random.default_rng(0).uniform(-5.0, 5.0, size=(4, 18)), jnp.float32)
    data = empty_data(robot, 4)
    data = jax.vmap(lambda c: data.replace(ctrl=c, qpos=data.qpos.at[2].set(0.12)))(ctrl)
    _flushed_output(capfd)

    def steps(model):
        step = jax.jit(jax.vmap(mjx.step, in_axes=(None, 0)))
        out = data
        for _ in range(5):
            out = step(model, out)
        return jax.block_until_ready(out)

    from mujoco.mjx.third_party.mujoco_warp import OverflowType

    quiet = steps(robot.model)
    assert (np.asarray(quiet._impl.overflow) & int(OverflowType.ITERATIONS)).any()  # the cap binds
    assert "iterations limit" not in _flushed_output(capfd)
    steps(mjx.put_model(mj_model(config), impl="warp"))  # MuJoCo Warp's own warnings
    assert "solver iterations limit reached" in _flushed_output(capfd)

    start = standing_state(robot)
    params = jnp.asarray(np.random.default_rng(1).uniform(size=(2, 4, 36)), jnp.float32)
    spec = RolloutSpec(num_steps=20, record_contacts=False)
    alone = rollout(robot, params[0], jnp.zeros(6, bool), start, spec)
    assert not (np.asarray(alone.invalid_reason) & InvalidReason.WARP_OVERFLOW).any()
    _flushed_output(capfd)
    nested = jax.jit(jax.vmap(lambda p: rollout(robot, p, jnp.zeros(6, bool), start, spec)))(params)
    assert (np.asarray(nested.invalid_reason) & InvalidReason.WARP_OVERFLOW).all()
    assert not np.asarray(nested.valid).any()
    assert "overflow" in _flushed_output(capfd)


def test_benchmark_settings_name_the_implementation(monkeypatch):
    """physics_frontier.py / batch_size.py settings "S/L[@...][@impl=I]": the implementation is part of
    the setting, and a setting without it is MJX's JAX implementation."""
    from tests.benchmark_runner import benchmark_module

    common = benchmark_module("common")
    assert common.parse_setting("4/4@impl=warp") == {"solver_iterations": 4, "ls_iterations": 4, "impl": "warp"}
    assert common.setting_label(RobotConfig(**common.parse_setting("4/4@impl=warp@dt=0.005"))) == "4/4@dt=0.005@impl=warp"
    assert common.setting_label(RobotConfig(**common.parse_setting("4/4@impl=jax"))) == "4/4"
    with pytest.raises(ConfigError, match="impl"):
        RobotConfig(**common.parse_setting("4/4@impl=cuda"))
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # batch_size.py imports common
    batch_size = benchmark_module("batch_size")
    args = batch_size._parse(["--impl", "warp", "--compare", "4/4"])
    assert batch_size._robot_config(args).impl == "warp" and batch_size._robot_config(args, args.compare).impl == "jax"


@needs_warp
def test_warp_runs_spread_over_two_devices(tmp_path):
    """MJX's Warp backend through `sharding.map_rows` on 2 forced CPU devices, each in its own process
    (`benchmarks/warp_devices.py`): a tiny model's steps and the project's rollout give one device's
    positions (a plain shard_map of Warp's model crashed jax 0.11.2's partitioner on its zero-sized
    arrays; `map_rows` makes them inside), and asking for Warp on several devices is no error."""
    out = tmp_path / "devices.jsonl"
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "warp_devices.py"), "--cpu-devices", "2",
                           "--batch", "8", "--steps", "5", "--variants", "single,map_rows,rollout_single,rollout",
                           "--timeout", "800", "--out", str(out)], capture_output=True, text=True, cwd=ROOT,
                          env=dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))),
                          timeout=1800)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = {row["variant"]: row for row in map(json.loads, out.read_text().splitlines())}
    assert all(row["exit"] == 0 and row["finite"] for row in rows.values()), rows
    assert rows["map_rows"]["devices"] == rows["rollout"]["devices"] == 2
    assert rows["map_rows"]["max_abs_diff"] <= 1e-5 and rows["rollout"]["max_abs_diff"] <= 1e-4, rows
    require_impl("warp")
