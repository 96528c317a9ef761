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


def _result(path, setting, rows):
    """A damage_skills.py result holding `rows` (repertoire, model, leg, valid, distance_median_m)."""
    keys = ("repertoire", "model", "leg", "valid", "distance_median_m")
    full = [{**dict(zip(keys, row)), "flipped": 1.0 - row[3], "distance_p90_m": row[4], "contact_lost": 0.5}
            for row in rows]
    path.write_text(json.dumps({"environment": {"device": "cpu", "date": "2026-11-28"},
                                "settings": {"setting": setting}, "rows": full}))
    return path


def test_two_damage_skills_results_are_compared_row_by_row(tmp_path, capsys):
    """compare_damage_skills.py pairs the rows by (repertoire, model, leg): A - B of each measure (None where a
    distance is missing), the largest |A - B| per measure, the rows only one result holds; bad input is one line."""
    compare = benchmark_module("compare_damage_skills")
    a = _result(tmp_path / "a.json", "4/4@impl=warp", [("hbr", "intact", None, 1.0, 0.0),
                                                       ("hbr", "removed", 0, 0.75, 0.30),
                                                       ("hbr", "weak", 1, 1.0, None)])
    b = _result(tmp_path / "b.json", "4/4", [("hbr", "intact", None, 1.0, 0.0), ("hbr", "removed", 0, 0.80, 0.25),
                                             ("hbr", "weak", 1, 1.0, 0.06), ("flat-2d", "intact", None, 1.0, 0.0)])
    out = tmp_path / "c.json"
    assert compare.main([str(a), str(b), "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["a"]["setting"] == "4/4@impl=warp" and result["b"]["setting"] == "4/4"
    rows = {(r["repertoire"], r["model"], r["leg"]): r for r in result["rows"]}
    assert list(rows) == [("hbr", "intact", None), ("hbr", "removed", 0), ("hbr", "weak", 1)]
    assert rows["hbr", "removed", 0]["valid"]["difference"] == pytest.approx(-0.05)
    assert rows["hbr", "removed", 0]["flipped"]["difference"] == pytest.approx(0.05)
    assert rows["hbr", "weak", 1]["distance_median_m"] == {"a": None, "b": 0.06, "difference": None}
    largest = result["largest_abs_difference"]
    assert largest["valid"] == pytest.approx(0.05) and largest["distance_median_m"] == pytest.approx(0.05)
    assert largest["contact_lost"] == 0.0
    assert result["only_in"] == {"a": [], "b": [["flat-2d", "intact", None]]}
    assert "largest |A - B|: valid 0.0500" in capsys.readouterr().out

    other = tmp_path / "other.json"
    other.write_text(json.dumps({"rows": []}))
    for args, message in (([str(a), str(tmp_path / "missing.json")], "not a damage_skills.py result"),
                          ([str(a), str(other)], "share no (repertoire, model, leg) row")):
        assert compare.main([*args, "--out", str(tmp_path / "never.json")]) == 2
        error = capsys.readouterr().err
        assert error.startswith("error: ") and message in error and error.count("\n") == 1
    assert not (tmp_path / "never.json").exists()
