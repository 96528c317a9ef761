"""benchmarks/damage_skills.py end to end at a tiny size (its `main` in this process): a row for every
(repertoire, condition) asked for, and rows that mean what they say."""

import json

import pytest

from hte_jax.sim.damage import stack_damages
from tests.benchmark_runner import benchmark_module, run_benchmark

damage_skills = benchmark_module("damage_skills")


@pytest.mark.slow
def test_damage_skills_benchmark(tmp_path):
    """Three skills of each shipped repertoire under removed and weak legs 1 and 4 and a slippery floor (about
    a minute on 2 cores: three programs compile, the standing states, the HBR skills, the flat rollouts)."""
    out = tmp_path / "damage.json"
    stdout = run_benchmark("damage_skills.py", "--models", "removed,weak,friction", "--legs", "1,4", "--skills", "3",
                           "--fraction", "0.5", "--friction", "0.4", "--out", str(out))
    result = json.loads(out.read_text())
    assert result["environment"]["device"] and result["environment"]["date"]
    assert result["command"].startswith("python benchmarks/damage_skills.py --models removed,weak,friction")
    assert result["settings"]["models"] == ["removed", "weak", "friction"] and result["settings"]["legs"] == [1, 4]
    conditions = [("intact", None), ("removed", 1), ("removed", 4), ("weak", 1), ("weak", 4), ("friction", None)]
    for kind in ("hbr", "flat-2d"):
        rows = [row for row in result["rows"] if row["repertoire"] == kind]
        assert [(row["model"], row["leg"]) for row in rows] == conditions
        assert len(set(result["sampled_rows"][kind])) == 3
        by = {(row["model"], row["leg"]): row for row in rows}
        intact = by["intact", None]
        # the reference: every shipped skill stays valid intact, at distance 0 from itself, losing no contact
        assert intact["valid"] == 1.0 and intact["flipped"] == 0.0 and intact["compared"] == 3
        assert intact["distance_median_m"] == intact["distance_p90_m"] == 0.0 and intact["contact_lost"] == 0.0
        assert intact["contact_feet"] == list(range(6)) and 0 < intact["contact"] < 1
        for row in rows:
            assert row["skills"] == 3 and 0 <= row["valid"] <= 1 and row["flipped"] <= 1 - row["valid"] + 1e-9
            assert row["invalid_reasons"]["FLIPPED"] == row["flipped"]
            assert row["fraction"] == (0.5 if row["model"] == "weak" else 1.0)
            assert row["friction"] == pytest.approx(0.4 if row["model"] == "friction" else 1.0)
            if row["model"] != "intact" and row["compared"]:
                assert row["distance_median_m"] > 0 and row["distance_p90_m"] >= row["distance_median_m"]
        for leg in (1, 4):
            removed = by["removed", leg]
            assert removed["contact_feet"] == [leg]
            if removed["compared"]:  # a removed leg's foot never touches the floor: all its intact contact lost
                assert removed["contact"] == 0.0 and removed["feet_contact"][leg] == 0.0
                assert removed["contact_lost"] == 1.0 and removed["contact_intact"] > 0
        assert by["friction", None]["contact_feet"] == list(range(6))
    assert "removed" in stdout and "dist med cm" in stdout and "lost %" in stdout


@pytest.mark.parametrize("args, message", [
    (["--models", "raised,melted"], "unknown damage model 'melted'"),
    (["--models", "raised,raised"], "names a model twice"),
    (["--legs", "1,6"], "--legs '1,6'"),
    (["--fraction", "1.5"], "damage fraction must be in (0, 1]"),
    (["--models", "friction", "--friction", "0"], "floor friction scale must be > 0"),
    (["--skills", "-1"], "--skills must be >= 0"),
    (["--repertoires", "hbr,8d"], "--repertoires 'hbr,8d'"),
    (["--setting", "4"], "--setting"),
])
def test_bad_inputs_are_one_line_errors(args, message, tmp_path, capsys):
    out = tmp_path / "never.json"
    assert damage_skills.main([*args, "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert error.startswith("error: ") and message in error and error.count("\n") == 1
    assert not out.exists()


def test_conditions_mix_models_in_one_batch():
    """Intact first, then each model on each leg (a fraction only where the model takes one), friction once."""
    items = damage_skills.conditions(("locked", "shortened", "friction"), (0, 5), 0.3, 0.6)
    assert [(item.model, item.leg) for item in items] == [
        ("intact", None), ("locked", 0), ("locked", 5), ("shortened", 0), ("shortened", 5), ("friction", None)]
    damage = stack_damages([item.damage for item in items])
    assert damage.legs.shape == (6, 6) and damage.legs.sum(axis=1).tolist() == [0, 1, 1, 1, 1, 0]
    assert damage.legs[2, 5] and damage.legs[3, 0]
    assert damage.fraction.tolist() == pytest.approx([1, 1, 1, 0.3, 0.3, 1])
    assert damage.friction.tolist() == pytest.approx([1, 1, 1, 1, 1, 0.6])
    assert len(set(damage.model[1:5].tolist())) == 2  # locked and shortened rows: different models, one batch
