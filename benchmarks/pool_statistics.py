"""Pool the episodes of several `maze_eval` runs into one set of statistics (the paper's, episode- and seed-level).

Each --run is LABEL=DIR[:VARIANT][@SEEDS]: the episodes of run folder DIR (its episodes.json or
episodes.json.gz), only VARIANT's if given, only the repertoire seeds SEEDS (comma-separated seed
indices of that run) if given, all under the name LABEL. E.g. the budget-matched 2D-RTE control,
whose runs cover seeds 1 and 3 only (`benchmarks/results/r4_matched_2d-rte_raised/`):

    python benchmarks/pool_statistics.py --out matched_statistics.json --key raised \\
        --run "2d-rte standard jax=R4_RAISED:2d-rte@1,3" --run "hte-spare=R4_RAISED:hte-spare@1,3" \\
        --run "2d-rte matched warp=MATCHED_RAISED" --run "2d-rte standard warp=STD_WARP_RAISED"

A replication's score is the median over the seeds it covers (`protocol_statistics`); the seeds of
different runs are paired by position (also in the seed-level tests), so give every run the same
number of seeds. Writes (or adds KEY to) --out and prints each label's quartiles (the paper's method)
and failure rate, its success rate with a 95 % Wilson interval and per-seed rates, and the
Bonferroni-corrected tests of each pair at the three levels.
"""

from __future__ import annotations

import argparse
import gzip
import json
from pathlib import Path

from hte_jax.online.statistics import PAPER_METHOD_HEADER, level_lines, protocol_statistics


def read_episodes(folder: Path) -> list[dict]:
    """The episode records of a maze_eval run folder."""
    plain, packed = folder / "episodes.json", folder / "episodes.json.gz"
    if plain.is_file():
        return json.loads(plain.read_text())["episodes"]
    if packed.is_file():
        return json.loads(gzip.decompress(packed.read_bytes()))["episodes"]
    raise SystemExit(f"error: {folder} holds no episodes.json(.gz)")


def pooled(spec: str) -> list[dict]:
    """The records of one --run LABEL=DIR[:VARIANT][@SEEDS], relabelled LABEL, seeds renumbered 0.."""
    label, _, rest = spec.partition("=")
    rest, _, seeds = rest.partition("@")
    folder, _, variant = rest.partition(":")
    if not label or not folder:
        raise SystemExit(f"error: --run {spec!r} is not LABEL=DIR[:VARIANT][@SEEDS]")
    keep = [int(s) for s in seeds.split(",")] if seeds else None
    out = []
    for r in read_episodes(Path(folder)):
        if (variant and r["variant"] != variant) or (keep is not None and r.get("seed", 0) not in keep):
            continue
        seed = keep.index(r.get("seed", 0)) if keep is not None else r.get("seed", 0)
        out.append({**r, "variant": label, "seed": seed})
    if not out:
        raise SystemExit(f"error: --run {spec!r} selects no episodes")
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", action="append", required=True, help="LABEL=DIR[:VARIANT][@SEEDS]")
    parser.add_argument("--out", type=Path, required=True, help="JSON file to write (KEY added if it exists)")
    parser.add_argument("--key", default="pooled", help="the entry of --out to write (default pooled)")
    args = parser.parse_args(argv)
    records = [r for spec in args.run for r in pooled(spec)]
    stats = protocol_statistics(records)
    stats.pop("medians")
    data = json.loads(args.out.read_text()) if args.out.is_file() else {}
    data[args.key] = stats
    args.out.write_text(json.dumps(data, indent=1) + "\n")
    print(PAPER_METHOD_HEADER)
    for name, v in stats["variants"].items():
        print(f"{name:24s} p25/p50/p75 {v['p25']:5.1f} {v['p50']:5.1f} {v['p75']:5.1f}  failed {v['failure_percent']:5.1f} %"
              f"  ({v['replications']} replications, {v['episodes']} episodes)")
    print("\n".join(level_lines(stats)))


if __name__ == "__main__":
    main()
