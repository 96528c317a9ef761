"""`experiments.fit_gp` on a short maze_eval run: the RTE GPs it rebuilds from episodes_<k>.npz are
the episodes' own, the fit raises their likelihood and fit.json says so, and bad input is refused
with one line and exit status 2."""

import json
import shutil

import jax
import numpy as np
import pytest

import experiments.maze_eval as maze_eval
from experiments.fit_gp import main as fit_main
from experiments.fit_gp import run_models
from hte_jax.online.gp import RTE_KERNEL, Kernel
from hte_jax.online.gp_fit import kernel_params, total_log_likelihood
from hte_jax.qd.io import read_checkpoint, save_checkpoint

RUN = ["--variant", "rte", "--damage", "none,leg1", "--replicates", "1", "--max-actions", "4", "--iterations", "50",
       "--roots", "1", "--no-progress"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """(run folder, the RTE GPs (B, L, ...) its episodes ended with)."""
    out = tmp_path_factory.mktemp("fit") / "run"
    saved = []
    original = maze_eval._save_batch

    def keep(path, result, *rest):
        saved.append(jax.tree.map(lambda x: x[:, 0], result.episodes.rte))  # K = 1 repertoire
        original(path, result, *rest)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(maze_eval, "_save_batch", keep)
        assert maze_eval.main([*RUN, "--out", str(out)]) == 0
    assert len(saved) == 1
    return out, saved[0]


def test_rebuilt_gps_are_the_episodes_own(run):
    folder, own = run
    rebuilt, info = run_models(folder, None)
    assert info["episodes"] == {"rte": 2} and sum(info["skipped"].values()) == 0
    np.testing.assert_array_equal(np.asarray(rebuilt.mask), np.asarray(own.mask))
    np.testing.assert_array_equal(np.asarray(rebuilt.count), np.asarray(own.count))
    assert int(own.mask.sum()) >= 2
    for name in ("inputs", "targets", "prior"):
        np.testing.assert_allclose(np.asarray(getattr(rebuilt, name)), np.asarray(getattr(own, name)), atol=1e-6)


def test_fit_writes_a_better_kernel(run, capsys):
    folder, own = run
    assert fit_main(["--run", str(folder), "--steps", "100"]) == 0
    line = capsys.readouterr().out.strip()
    assert "\n" not in line and line.startswith("RTE kernel fitted on 2 episodes") and "fit.json" in line
    fit = json.loads((folder / "fit.json").read_text())
    assert fit["initial"] == {"kind": RTE_KERNEL.kind, "length_scale": RTE_KERNEL.length_scale,
                              "variance": RTE_KERNEL.variance, "noise": RTE_KERNEL.noise}
    assert fit["observations"] == int(own.mask.sum()) and len(fit["trace"]) == 101
    likelihood = fit["log_likelihood"]
    assert likelihood["fitted"] > likelihood["initial"]
    assert likelihood["initial"] == fit["trace"][0] and likelihood["fitted"] == fit["trace"][-1]
    # both are the likelihoods of the episodes' own GPs under those kernels
    fitted = Kernel(**fit["fitted"])
    for kernel, value in ((RTE_KERNEL, likelihood["initial"]), (fitted, likelihood["fitted"])):
        assert float(total_log_likelihood(kernel_params(kernel), own, kernel.kind)) == pytest.approx(value, abs=1e-3)
    assert (fitted.length_scale, fitted.variance, fitted.noise) != (0.03, 0.01, 0.001)


def _rewrite(source, target, change):
    """A copy of run folder `source` at `target` whose episodes_0.npz arrays went through `change`."""
    shutil.copytree(source, target, ignore=shutil.ignore_patterns("fit.json"))
    arrays, header = read_checkpoint(target / "episodes_0.npz")
    change(arrays)
    save_checkpoint(target / "episodes_0.npz", arrays, header["metadata"], compress=True)
    return target


def test_bad_input_is_refused_in_one_line(run, tmp_path, capsys):
    folder, _ = run

    def moved(arrays):
        arrays["predicted"] = arrays["predicted"] + np.float32(0.1)

    (tmp_path / "empty").mkdir()
    cases = [
        (["--run", str(tmp_path / "missing")], "no such folder"),
        (["--run", str(tmp_path / "empty")], "not a maze_eval run folder"),
        (["--run", str(folder), "--variant", "nope"], "unknown variant 'nope'"),
        (["--run", str(folder), "--variant", "hte"], "no HBR episode with an action"),
        (["--run", str(folder), "--steps", "0"], "--steps must be an integer >= 1"),
        (["--run", str(_rewrite(folder, tmp_path / "other", moved))], "are not the ones the run planned with"),
    ]
    for argv, message in cases:
        assert fit_main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and err.startswith("error:") and message in err, err
    assert not (tmp_path / "other" / "fit.json").exists()
