"""Two `damage_skills.py` results side by side: the same conditions under two backends, solver settings or
devices, row by row (repertoire, damage model, leg), and the largest difference of each measure.

    python benchmarks/compare_damage_skills.py warp.json jax.json --out warp_vs_jax.json

Compares valid, flipped, distance_median_m, distance_p90_m and contact_lost over the rows both results hold
(A - B; a distance is None where no skill was compared); prints a table and writes JSON (each result's file,
setting, device and date, the rows, the largest |A - B| per measure and the rows only one result holds).
Bad input: one `error: ...` line on stderr, exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

MEASURES = ("valid", "flipped", "distance_median_m", "distance_p90_m", "contact_lost")


def _key(row: dict) -> tuple:
    return row["repertoire"], row["model"], row["leg"]


def _load(path: Path) -> dict:
    try:
        result = json.loads(path.read_text())
        rows = {_key(row): row for row in result["rows"]}
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise ValueError(f"{path}: not a damage_skills.py result ({error})") from None
    return {"result": result, "rows": rows}


def compare(a: dict, b: dict) -> dict:
    """Rows of A and B (`_load`) paired by (repertoire, model, leg): each measure's A, B and A - B, the largest
    |A - B| per measure, and the keys only one of them holds."""
    shared = [key for key in a["rows"] if key in b["rows"]]
    if not shared:
        raise ValueError("the two results share no (repertoire, model, leg) row")
    rows, largest = [], dict.fromkeys(MEASURES, 0.0)
    for key in shared:
        row = {"repertoire": key[0], "model": key[1], "leg": key[2]}
        for name in MEASURES:
            x, y = a["rows"][key][name], b["rows"][key][name]
            difference = None if x is None or y is None else x - y
            row[name] = {"a": x, "b": y, "difference": difference}
            if difference is not None:
                largest[name] = max(largest[name], abs(difference))
        rows.append(row)
    only = {"a": [list(k) for k in a["rows"] if k not in b["rows"]],
            "b": [list(k) for k in b["rows"] if k not in a["rows"]]}
    return {"rows": rows, "largest_abs_difference": largest, "only_in": only}


def _about(path: Path, loaded: dict) -> dict:
    result = loaded["result"]
    return {"file": str(path), "setting": result.get("settings", {}).get("setting"),
            "device": result.get("environment", {}).get("device"), "date": result.get("environment", {}).get("date")}


def _cell(value) -> str:
    return "-" if value is None else f"{value:+.3f}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a", type=Path, help="a damage_skills.py JSON result")
    p.add_argument("b", type=Path, help="another, compared against")
    p.add_argument("--out", type=Path, required=True, help="JSON path to write")
    args = p.parse_args(argv)
    try:
        a, b = _load(args.a), _load(args.b)
        comparison = compare(a, b)
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"A: {args.a} ({_about(args.a, a)['setting']}), B: {args.b} ({_about(args.b, b)['setting']}); A - B")
    print(f"{'repertoire':10} {'model':10} {'leg':>3} " + " ".join(f"{name:>17}" for name in MEASURES))
    for row in comparison["rows"]:
        leg = "-" if row["leg"] is None else row["leg"]
        print(f"{row['repertoire']:10} {row['model']:10} {leg:>3} "
              + " ".join(f"{_cell(row[name]['difference']):>17}" for name in MEASURES))
    print("largest |A - B|: " + ", ".join(f"{k} {v:.4f}" for k, v in comparison["largest_abs_difference"].items()))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"a": _about(args.a, a), "b": _about(args.b, b), **comparison}, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
