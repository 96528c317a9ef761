"""The paper's protocol through `experiments.maze_eval`: 2D-RTE and APROL episodes on two
repertoire-seed folders, the per-seed records, the statistics and the figures, and the protocol's
variant and damage set (a separate module from test_episode.py so that pytest-xdist can run the two
side by side)."""

import json

import matplotlib.image
import numpy as np
import pytest

from experiments.maze_eval import main as maze_main
from hte_jax.flat.store import shipped_flat_path
from hte_jax.geometry import relative_pose
from hte_jax.qd.io import read_checkpoint

# With test_seed_sets, which runs these 2D-RTE episodes: one worker compiles their programs once.
pytestmark = pytest.mark.xdist_group("rte_episodes")


def _records(out):
    return json.loads((out / "episodes.json").read_text())["episodes"]


@pytest.mark.slow
def test_flat_and_aprol_episodes_on_two_seeds_and_protocol_outputs(tmp_path):
    seeds = tmp_path / "seeds"
    for seed in ("seed0", "seed1"):  # two "repertoire seeds", both the shipped files
        (seeds / seed).mkdir(parents=True)
        for kind, name in (("2d", "flat2d.npz"), ("aprol", "aprol.npz")):
            (seeds / seed / name).symlink_to(shipped_flat_path(kind))
    out = tmp_path / "flat"
    args = ["--variant", "2d-rte,aprol", "--damage", "none,leg1", "--replicates", "2", "--max-actions", "2",
            "--iterations", "50", "--roots", "1", "--repertoire-dir", str(seeds), "--out", str(out), "--no-progress"]
    assert maze_main(args) == 0
    for k, (seed, kind) in enumerate([(0, "flat-2d"), (0, "flat-2d-set"), (1, "flat-2d"), (1, "flat-2d-set")]):
        arrays, header = read_checkpoint(out / f"episodes_{k}.npz")
        assert header["metadata"]["repertoire"]["kind"] == kind and header["metadata"]["seed"] == seed
        assert (arrays["taken"] == 2).all() and (arrays["patterns"] == -1).all() and (arrays["errors"] == 0).all()
        for i in range(4):
            track = arrays["trajectory"][i]
            for j in range(2):
                np.testing.assert_allclose(arrays["observed"][i, j], relative_pose(track[4 * j], track[4 * j + 4]),
                                           atol=1e-4)
        if kind == "flat-2d":
            assert (arrays["map"] == 0).all() and (arrays["action"] == arrays["planned"]).all()
        else:  # APROL: 21 repertoires; its choice is any repertoire's skill, predicted from that repertoire's GP
            assert header["metadata"]["repertoire"]["repertoires"] == 21
            assert ((arrays["map"] >= 0) & (arrays["map"] < 21)).all()
    records = _records(out)
    assert sorted({r["seed"] for r in records}) == [0, 1] and len(records) == 16
    statistics = json.loads((out / "statistics.json").read_text())
    assert set(statistics["variants"]) == {"2d-rte", "aprol"}
    # 2 damages x 2 replicates, each the median over the 2 seeds
    assert statistics["variants"]["aprol"]["replications"] == 4 and statistics["variants"]["aprol"]["episodes"] == 8
    assert statistics["variants"]["aprol"]["seeds_per_median"] == 2
    assert len(statistics["tests"]) == 1 and statistics["tests"][0]["method"] == "paper"
    # the episode and seed levels: per seed success cells, the two seeds paired
    aprol = statistics["success"]["aprol"]
    assert set(aprol["seeds"]) == {"0", "1"} and set(aprol["damages"]) == {"none", "leg1"}
    assert aprol["pooled"]["episodes"] == 8
    assert len(statistics["episode_tests"]["success"]["pairs"]) == 1
    assert statistics["seed_tests"]["success_rate"]["pairs"][0]["seeds"] == 2
    for name in ("fig6_actions", "fig7_failures", "maze_variants", "maze_aprol"):
        image = matplotlib.image.imread(out / "plots" / f"{name}.png")
        assert image.ndim == 3 and image.std() > 0


def test_protocol_sets_the_papers_variants_and_damages(capsys):
    assert maze_main(["--protocol", "paper", "--damage-model", "locked", "--show-config"]) == 0
    config = json.loads(capsys.readouterr().out)
    assert config["variants"] == "perfect-hte,hte,2d-rte,8d-rte,aprol,random-hte"
    assert config["damages"] == "all" and config["damage_model"] == "locked"
    assert config["reflex_tilt"] == 0 and config["reflex_release"] == 0  # the paper's robot


def test_hte_jax_protocol_fixes_the_reflex_and_flags_override_it(capsys):
    assert maze_main(["--protocol", "hte-jax", "--seed", "27", "--show-config"]) == 0
    config = json.loads(capsys.readouterr().out)
    assert config["variants"] == "perfect-hte,hte-spare,perfect-spare,hte,rte,2d-rte"
    assert config["damages"] == "all" and config["seed"] == 27
    assert config["reflex_tilt"] == 0.3 and config["reflex_release"] == 0.15
    assert maze_main(["--protocol", "hte-jax", "--reflex-release", "0", "--variant", "hte-spare,rte",
                      "--show-config"]) == 0
    config = json.loads(capsys.readouterr().out)
    assert config["reflex_release"] == 0 and config["reflex_tilt"] == 0.3 and config["variants"] == "hte-spare,rte"


def test_the_ablations_protocol_runs_each_half_of_hte_spare_beside_it(capsys):
    assert maze_main(["--protocol", "ablations", "--show-config"]) == 0
    config = json.loads(capsys.readouterr().out)
    assert config["variants"] == "hte-spare,hte-sense,rte-spare,rte,perfect-spare"
    assert config["damages"] == "all" and (config["reflex_tilt"], config["reflex_release"]) == (0.3, 0.15)
