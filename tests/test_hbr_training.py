"""HBR training end to end (tiny preset), resume, re-simulation of stored elites, HBR files (acceptance 1, 5)."""

import csv
import json

import jax
import jax.numpy as jnp
import matplotlib.image
import numpy as np
import pytest

from experiments.train_hbr import main as train_main
from hte_jax.hbr.hierarchy import execute_skill, execute_step
from hte_jax.geometry import compose_pose, planar_pose
from hte_jax.hbr.middle import PRIMARY, evaluate_controllers
from hte_jax.hbr.store import load_hbr
from hte_jax.hbr.training import PRESETS, normalised_config, preset, train_hbr, with_overrides
from hte_jax.errors import ConfigError
from experiments.measure_steps import main as measure_main
from hte_jax.qd.io import CheckpointError, prepare_run_dir, read_checkpoint, save_checkpoint
from hte_jax.sim import standing_state
from tests.benchmark_runner import run_benchmark_process  # resume_kill.py kills and restarts commands: its own process
from tests import golden

# Bit for bit: the golden output of the tiny HBR and resumed runs against it. Group hbr_tiny: the files that run
# the tiny HBR's programs (test_benchmarks_hbr, test_interrupts) on one worker, one after the other, so that only
# the first compiles them. The tiny run (a module fixture) takes minutes: its first test has more than 600 s.
pytestmark = [pytest.mark.exact_numerics, pytest.mark.xdist_group("hbr_tiny"), pytest.mark.timeout(1200)]

LAYERS = ("bottom", "middle", "top")


@pytest.fixture(scope="module")
def start(robot):
    return standing_state(robot)


tiny_run = golden.run_fixture("hbr_tiny")


def _rows(path):
    with open(path) as handle:
        return list(csv.DictReader(handle))


@pytest.mark.slow
def test_tiny_preset_writes_a_complete_hbr(tiny_run):
    config = preset("tiny")
    summary = json.loads((tiny_run / "summary.json").read_text())
    hbr, top_task, meta = load_hbr(tiny_run / "hbr.npz")
    for layer in LAYERS:
        schedule = getattr(config, layer)
        assert summary["layers"][layer]["evaluations"] == schedule.init_size + schedule.generations * schedule.batch_size
        elites = int(getattr(hbr, layer).filled.sum())
        assert elites == summary["statistics"][layer]["elites"] == summary["layers"][layer]["filled"] > 0
        rows = _rows(tiny_run / layer / "metrics.csv")
        assert [int(r["generation"]) for r in rows] == list(range(schedule.generations + 1))
        filled = [int(r["filled"]) for r in rows]
        assert filled == sorted(filled) and filled[-1] == elites
        for descriptor in np.asarray(getattr(hbr, layer).descriptors)[np.asarray(getattr(hbr, layer).filled)]:
            assert ((descriptor >= 0) & (descriptor <= 1)).all()
    middle = np.asarray(hbr.middle.descriptors)[np.asarray(hbr.middle.filled)]
    assert set(np.unique(middle[:, PRIMARY:])) <= {0.0, 1.0}
    assert summary["statistics"]["middle"]["contact_patterns"] == len({tuple(b) for b in middle[:, PRIMARY:]})
    bands = summary["statistics"]["top"]["fitness_by_distance"]
    assert sum(band["cells"] for band in bands) == summary["statistics"]["top"]["elites"]
    assert meta["training"]["config"] == config.to_dict()
    assert top_task == config.top_task and hbr.middle_task == config.middle_task
    filled = np.asarray(hbr.middle.filled)  # the step model measured at the end of training
    assert summary["step_model"]["starts"] == config.step_starts == 2
    steps, spread = np.asarray(hbr.step_model.steps)[filled], np.asarray(hbr.step_model.spread)[filled]
    assert np.all((steps > 0) & (steps < 1)) and np.all(np.isfinite(spread) & (spread >= 0))
    for name in ("top_xy_fitness", "middle_xy_yaw_patterns", "bottom_projections", "bottom_metrics", "middle_metrics",
                 "top_metrics"):
        image = matplotlib.image.imread(tiny_run / "plots" / f"{name}.png")
        assert image.ndim == 3 and image.shape[0] > 100 and image.std() > 0


@pytest.mark.slow
def test_tiny_run_matches_the_golden_output(tiny_run):
    golden.check("hbr_tiny", tiny_run)


@pytest.mark.slow
def test_killed_run_resumes_bit_identical(tiny_run, tmp_path):
    class Killed(Exception):
        pass

    def kill(layer, block, state, row):
        if layer == "middle" and block == 0:
            raise Killed

    out = tmp_path / "killed"
    with pytest.raises(Killed):
        train_hbr(preset("tiny"), out, progress=False, on_block=kill, plots=False)
    assert (out / "middle" / "checkpoint.npz").exists() and not (out / "top").exists()
    first = {layer: [float(r["wall_time_s"]) for r in _rows(out / layer / "metrics.csv")] for layer in ("bottom", "middle")}
    outcome = train_hbr(preset("tiny"), out, resume_run=True, progress=False, plots=False)
    # Wall times count every session: the bottom layer, done before the kill, keeps the first session's
    # seconds; the middle layer's rows count on from its kept block 0.
    layers = outcome.summary["layers"]
    assert layers["bottom"]["wall_time_s"] == first["bottom"][-1] > 0
    middle = [float(r["wall_time_s"]) for r in _rows(out / "middle" / "metrics.csv")]
    assert middle[:2] == first["middle"][:2] and np.all(np.diff(middle) > 0) and layers["middle"]["wall_time_s"] == middle[-1]
    resumed, _ = read_checkpoint(out / "hbr.npz")
    reference, _ = read_checkpoint(tiny_run / "hbr.npz")
    assert resumed.keys() == reference.keys()
    for name in reference:
        np.testing.assert_array_equal(resumed[name], reference[name], err_msg=name)
    for layer in LAYERS:
        strip = lambda rows: [{k: v for k, v in r.items() if k != "wall_time_s"} for r in rows]  # noqa: E731
        assert strip(_rows(out / layer / "metrics.csv")) == strip(_rows(tiny_run / layer / "metrics.csv"))


@pytest.mark.slow
def test_sigkilled_command_resumes_bit_identical(tiny_run, tmp_path):
    """benchmarks/resume_kill.py on the command: `train_hbr --preset tiny` SIGKILLed in the bottom layer's
    second block, its resume SIGKILLed between the middle layer's first checkpoint's temporary file and
    its rename, then resumed to the end: the same hbr.npz, statistics and metrics as `tiny_run`, the
    temporary file left by the kill in the way of nothing."""
    out = tmp_path / "kill.json"
    stdout = run_benchmark_process("resume_kill.py", "--scenarios", "bottom:block1+middle:write0", "--reference", str(tiny_run),
                           "--work-dir", str(tmp_path / "work"), "--out", str(out))
    (row,) = json.loads(out.read_text())["scenarios"]
    first, second = row["kills"]
    assert first["killed"] and first["folder"]["layers"]["bottom"]["generation"] == 1
    assert first["landed"].startswith("bottom: ") and first["folder"]["layers"]["middle"]["generation"] is None
    assert second["killed"] and second["landed"] == "middle: block 0's checkpoint: temp file written, not renamed"
    (temporary,) = second["temporary_files"]
    assert temporary.startswith("middle/.checkpoint.npz.tmp-") and second["folder"]["layers"]["middle"]["generation"] is None
    assert set(row["temporary_files_at_end"]) <= {temporary}  # the resume left none of its own
    assert row["resumes"] == 2 and row["arrays_compared"] >= 16 and row["arrays_differing"] == []
    assert row["header_identical"] and row["statistics_identical"] and row["metrics_differing"] == []
    assert row["identical"] and "1 of 1 scenarios identical" in stdout


@pytest.mark.slow
def test_cli_refuses_to_clobber_or_mix_configurations(tiny_run, capsys):
    assert train_main(["--preset", "tiny", "--out", str(tiny_run)]) == 2
    assert "--resume" in capsys.readouterr().err
    assert train_main(["--preset", "tiny", "--out", str(tiny_run), "--resume", "--seed", "5"]) == 2
    assert "seed" in capsys.readouterr().err
    assert train_main(["--preset", "huge"]) == 2
    assert "unknown preset" in capsys.readouterr().err
    assert train_main(["--middle-init-size", "20", "--middle-batch-size", "16"]) == 2
    assert "middle.init_size" in capsys.readouterr().err
    assert train_main(["--top-mutation-rate", "lots"]) == 2
    assert "top.mutation_rate" in capsys.readouterr().err


def test_runs_started_before_a_new_setting_still_resume(tmp_path):
    """A config.json written before `bottom_fitness` existed resumes under its default, and only under it."""
    config = PRESETS["tiny"].to_dict()
    old = {key: value for key, value in config.items() if key != "bottom_fitness"}
    (tmp_path / "config.json").write_text(json.dumps(old))
    assert prepare_run_dir(tmp_path, config, True, normalise=normalised_config) == tmp_path
    genes = with_overrides(PRESETS["tiny"], {"bottom_fitness": "genes"}).to_dict()
    with pytest.raises(ConfigError, match="differs in: bottom_fitness"):
        prepare_run_dir(tmp_path, genes, True, normalise=normalised_config)


def test_every_preset_value_can_be_overridden():
    config = with_overrides(PRESETS["gpu"], {"middle.generations": "7", "seed": "3", "contact_threshold": 0.25})
    assert (config.middle.generations, config.seed, config.contact_threshold) == (7, 3, 0.25)
    assert config.top == PRESETS["gpu"].top
    with pytest.raises(ConfigError, match="unknown setting 'middle.colour'"):
        with_overrides(config, {"middle.colour": 1})
    genes = with_overrides(config, {"bottom_fitness": "genes"})
    assert genes.bottom_task.fitness == "genes" and config.bottom_task.fitness == "commands"
    with pytest.raises(ConfigError, match="bottom_fitness must be one of"):
        with_overrides(config, {"bottom_fitness": "energy"})
    eta = with_overrides(config, {"middle.eta_m": "20"})
    assert eta.middle.map_elites_config(0.0).eta_m == 20.0 and config.middle.eta_m == 10.0
    with pytest.raises(ConfigError, match="middle.mutation_rate"):
        with_overrides(config, {"middle.mutation_rate": "2"})
    for name in ("cpu", "gpu", "paper"):
        schedule = PRESETS[name]
        assert (schedule.bottom.mutation_rate, schedule.middle.mutation_rate, schedule.top.mutation_rate) == (0.17, 0.11, 0.14)
    paper = PRESETS["paper"]
    # The paper's evaluation counts: 5001, 30000 and 20000 generations of 200.
    assert paper.bottom.evaluations == pytest.approx(5001 * 200, rel=0.01)
    assert paper.middle.evaluations == pytest.approx(30000 * 200, rel=0.01)
    assert paper.top.evaluations == pytest.approx(20000 * 200, rel=0.01)


@pytest.mark.slow
def test_stored_middle_elites_reproduce_when_re_simulated(tiny_run, robot, start):
    """Hierarchical execution of a middle elite (its target -> nearest elite -> controller) from
    the standing state reproduces its stored primary descriptor (to 1e-4 for the reported
    sample when it is the first; all elites re-simulated through their stored controllers)."""
    hbr, _, _ = load_hbr(tiny_run / "hbr.npz")
    count = int(hbr.middle.filled.sum())
    stored = np.asarray(hbr.middle.descriptors)[:count]
    again = evaluate_controllers(robot, start, hbr.middle_task, hbr.middle_params[:count])
    np.testing.assert_allclose(np.asarray(again.descriptors), stored, atol=1e-4)
    np.testing.assert_allclose(np.asarray(again.fitnesses), np.asarray(hbr.middle.fitnesses)[:count], atol=1e-4)
    first = np.flatnonzero(np.asarray(hbr.middle.extras["medoid"])[:count] == 0)
    assert first.size > 0
    batch = first.size
    starts = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), start)
    here = jnp.broadcast_to(planar_pose(start.qpos[:3], start.qpos[3:7]), (batch, 3))
    motion = hbr.middle_task.denormalise(jnp.asarray(stored[first, :PRIMARY]))
    target = compose_pose(here, motion)
    step = execute_step(robot, hbr, starts, jnp.zeros((batch, 6), bool), target, jnp.full(batch, -1))
    chosen = np.asarray(step.middle_index)
    np.testing.assert_allclose(stored[chosen, :PRIMARY], stored[first, :PRIMARY], atol=0.02)
    measured = np.asarray(hbr.middle_task.normalise(step.displacement))
    np.testing.assert_allclose(measured, stored[chosen, :PRIMARY], atol=1e-3)


@pytest.mark.slow
def test_top_skills_replay_through_hierarchical_execution(tiny_run, robot, start):
    """Deployment decodes a skill exactly as training did: same middle elites, same final position."""
    hbr, top_task, _ = load_hbr(tiny_run / "hbr.npz")
    filled = np.flatnonzero(np.asarray(hbr.top.filled))
    batch = filled.size
    starts = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), start)
    skill = execute_skill(robot, hbr, hbr.top.genotypes[filled], starts)
    assert bool(skill.valid.all())
    np.testing.assert_array_equal(np.asarray(skill.steps.middle_index).T, np.asarray(hbr.top.extras["middle_indices"])[filled])
    np.testing.assert_allclose(np.asarray(top_task.normalise(skill.displacement[:, :2])),
                               np.asarray(hbr.top.descriptors)[filled], atol=1e-4)


@pytest.mark.slow
def test_hbr_files_are_checked_on_load(tiny_run, tmp_path):
    arrays, header = read_checkpoint(tiny_run / "hbr.npz")
    meta = header["metadata"]

    def write(name, **changes):
        path = tmp_path / f"{name}.npz"
        save_checkpoint(path, {**arrays, **changes}, meta)
        return path

    with pytest.raises(CheckpointError, match="middle_genotypes has shape"):
        load_hbr(write("shape", middle_genotypes=arrays["middle_genotypes"][:, :17]))
    nan = arrays["top_fitnesses"].copy()
    nan[0] = np.nan
    with pytest.raises(CheckpointError, match="top_fitnesses holds NaN"):
        load_hbr(write("nan", top_fitnesses=nan))
    dangling = arrays["top_extra_middle_indices"].copy()
    dangling[0, 0] = 10**6
    with pytest.raises(CheckpointError, match="refer to middle elites"):
        load_hbr(write("dangling", top_extra_middle_indices=dangling))
    missing = {k: v for k, v in arrays.items() if k != "bottom_genotypes"}
    path = tmp_path / "missing.npz"
    save_checkpoint(path, missing, meta)
    with pytest.raises(CheckpointError, match="missing 'bottom_genotypes'"):
        load_hbr(path)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes((tiny_run / "hbr.npz").read_bytes()[:500])
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_hbr(truncated)
    with pytest.raises(CheckpointError, match="not an HBR file"):
        load_hbr(tiny_run / "top" / "checkpoint.npz")


@pytest.mark.slow
def test_measure_steps_cli_adds_a_step_model(tiny_run, tmp_path, capsys):
    out = tmp_path / "measured.npz"
    assert measure_main(["--hbr", str(tiny_run), "--out", str(out), "--starts", "1"]) == 0
    trained, _, _ = load_hbr(tiny_run / "hbr.npz")
    measured, _, meta = load_hbr(out)
    filled = np.asarray(trained.middle.filled)
    assert meta["step_model"]["starts"] == 1 and meta["training"] == load_hbr(tiny_run / "hbr.npz")[2]["training"]
    np.testing.assert_array_equal(np.asarray(measured.step_model.spread)[filled], 0.0)  # one start: no spread
    np.testing.assert_array_equal(measured.middle.genotypes, trained.middle.genotypes)
    capsys.readouterr()
    assert measure_main(["--hbr", str(tiny_run), "--starts", "0"]) == 2
    assert measure_main(["--hbr", str(tmp_path / "missing.npz")]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 2 and "--starts must be >= 1" in errors[0] and "missing.npz" in errors[1]
