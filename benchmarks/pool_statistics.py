"""Pool the episodes of several `maze_eval` runs into one set of statistics (the paper's; episode, seed, world level).

Each --run is LABEL=DIR[&DIR...][+DIR[&DIR...]...][:VARIANT][@SEEDS]: the episodes of run folder DIR (its
episodes.json or episodes.json.gz; a run cut before its end, its finished batch files episodes_<k>.npz), only
VARIANT's if given, only the repertoire seeds SEEDS (comma-separated seed indices of that run) if given, only
the damages matching --damage (a regular expression, whole label) if given, all under the name LABEL. E.g. the
budget-matched 2D-RTE control, whose runs cover seeds 1 and 3 only (`benchmarks/results/r4_matched_2d-rte_raised/`):

    python benchmarks/pool_statistics.py --out matched_statistics.json --key raised \\
        --run "2d-rte standard jax=R4_RAISED:2d-rte@1,3" --run "hte-spare=R4_RAISED:hte-spare@1,3" \\
        --run "2d-rte matched warp=MATCHED_RAISED" --run "2d-rte standard warp=STD_WARP_RAISED"

A replication's score is the median over the seeds it covers (`protocol_statistics`); the seeds of
different runs are paired by position (also in the seed-level tests), so give every run the same
number of seeds. Folders joined by & hold different seeds of the same replications (e.g. `maze_eval
--seeds 0 --impl jax` and `--seeds 1,2,3 --impl warp` over one --repertoire-dir): their episodes are
merged as they are, each keeping its seed, sorted by seed; two folders holding the same (variant, seed,
damage, replicate) stop the script. Parts joined by + (a folder, or folders joined by &) are worlds
(e.g. one run per maze) pooled under one label: each part's replicates follow the parts' before it
(different worlds' episodes are different replications) and its episodes carry "world", the part's
position; every run then names the same number of worlds, paired by position in "world_level" (the seed
level's tests with the world in place of the seed). & binds tighter than +: "A&B+C&D" is two worlds, the
seeds of A and B then those of C and D. Writes (or adds KEY to) --out and prints each label's quartiles
(the paper's method) and failure rate, its success rate with a 95 % Wilson interval and per-seed rates,
and the Bonferroni-corrected tests of each pair at each level; --summary and --figure write
`evaluation.summarise` and Fig. 6 of the episodes.

Each --cells is LABEL=FILE:KEY[:VARIANT]: the per-seed cells (episodes, successes, median actions) of LABEL's
other seeds, read from KEY in FILE (a statistics file this script wrote: its "seed_cells" where it has them, else
its "success"; VARIANT, default LABEL, names the variant there), for seeds whose episodes are no longer at hand.
Their seeds must differ from the seeds LABEL has already; a label may have cells and no --run. The entry then also
holds "seed_cells": `statistics.cell_statistics` of every seed (the files' and the runs'): pooled success with its
interval, Fisher's tests of the pooled counts and the seed-level tests; the other entries cover the runs'
episodes alone. E.g. ten seeds, seeds 0-3 from an earlier file:

    python benchmarks/pool_statistics.py --out s.json --key r10 --run "hte=R4_TO_9:hte" \\
        --cells "hte=benchmarks/results/r4_raised_h200x4_2026-11-28/statistics_hte-jax_raised.json:r4"
"""

from __future__ import annotations

import argparse
import functools
import gzip
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path

from hte_jax.errors import ConfigError
from hte_jax.online.evaluation import summarise
from hte_jax.online.plots import plot_protocol_box
from hte_jax.online.statistics import (PAPER_METHOD_HEADER, SEED_QUANTITIES, cell_statistics, level_lines,
                                       p_text, protocol_statistics, rank_test_text, rates_text, seed_cells,
                                       seed_level_tests, success_rates)
from hte_jax.qd.io import read_checkpoint

WORLD_SAMPLE = ("world level: the world (a run folder pooled with +, e.g. a maze) is the unit, each label's value per "
                "world (its episodes of all damages and seeds there) compared over the worlds, paired by position; "
                "exact two-sided Wilcoxon signed-rank (`seed_level_tests` with the world in place of the seed: "
                "its seed fields count worlds), Bonferroni over the pairs; min_p is the smallest p the ranked "
                "worlds can give")


@functools.cache
def read_episodes(folder: Path) -> list[dict]:
    """The episode records of a maze_eval run folder (of its finished batches if the run did not finish)."""
    plain, packed = folder / "episodes.json", folder / "episodes.json.gz"
    if plain.is_file():
        return json.loads(plain.read_text())["episodes"]
    if packed.is_file():
        return json.loads(gzip.decompress(packed.read_bytes()))["episodes"]
    batches = sorted(folder.glob("episodes_*.npz"), key=lambda p: int(p.stem.removeprefix("episodes_")))
    if not batches:
        raise ConfigError(f"{folder} holds no episodes.json(.gz) or finished batch (episodes_<k>.npz)")
    print(f"note: {folder}: a partial run, no episodes.json(.gz); read its {len(batches)} finished batch file(s)",
          file=sys.stderr)
    return [r for path in batches for r in read_checkpoint(path)[1]["metadata"]["records"]]


def pooled(spec: str, damage: str | None = None) -> tuple[list[dict], int]:
    """The records of one --run (damages fully matching `damage`), relabelled LABEL, seeds renumbered 0.. (with
    SEEDS), the folders joined by & merged (`merged_episodes`), the replicates of each world (a part joined by +)
    after the worlds' before it; and how many worlds."""
    label, _, rest = spec.partition("=")
    rest, _, seeds = rest.partition("@")
    folders, _, variant = rest.partition(":")
    if not label or not folders:
        raise ConfigError(f"--run {spec!r} is not LABEL=DIR[&DIR...][+DIR[&DIR...]...][:VARIANT][@SEEDS]")
    keep = [int(s) for s in seeds.split(",")] if seeds else None

    def selected(r: dict) -> bool:
        return not ((variant and r["variant"] != variant) or (keep is not None and r.get("seed", 0) not in keep)
                    or (damage is not None and not re.fullmatch(damage, r["damage"])))

    out, offset, worlds = [], 0, folders.split("+")
    for world, group in enumerate(worlds):
        records = merged_episodes(group.split("&"), selected, spec)
        for r in records:
            seed = keep.index(r.get("seed", 0)) if keep is not None else r.get("seed", 0)
            where = {"world": world} if len(worlds) > 1 else {}
            out.append({**r, "variant": label, "seed": seed, "replicate": offset + r["replicate"], **where})
        offset += 1 + max((r["replicate"] for folder in group.split("&") for r in read_episodes(Path(folder))),
                          default=-1)
    if not out:
        raise ConfigError(f"--run {spec!r} selects no episodes")
    return out, len(worlds)


def merged_episodes(folders: list[str], selected: Callable[[dict], bool], spec: str) -> list[dict]:
    """The `selected` episode records of run folders holding different seeds of the same replications, sorted by
    seed (stable); ConfigError if two folders hold the same (variant, seed, damage, replicate)."""
    holder, out = {}, []
    for folder in folders:
        records = [r for r in read_episodes(Path(folder)) if selected(r)]
        keys = {(r["variant"], r.get("seed", 0), r["damage"], r["replicate"]): folder for r in records}
        for key in keys:
            if key in holder:
                variant, seed, damage, replicate = key
                raise ConfigError(f"--run {spec!r}: {holder[key]} and {folder} both hold variant {variant!r}, "
                                  f"seed {seed}, damage {damage!r}, replicate {replicate} (& joins runs of other seeds)")
        holder.update(keys)
        out += records
    return sorted(out, key=lambda r: r.get("seed", 0))


def world_level(records: list[dict]) -> dict:
    """The seed level's statistics with each record's world in place of its seed."""
    by_world = [{**r, "seed": r["world"]} for r in records]
    return {"sample": WORLD_SAMPLE, "per_world": {v: c["seeds"] for v, c in success_rates(by_world).items()},
            **{q: seed_level_tests(by_world, q) for q in SEED_QUANTITIES}}


def world_lines(level: dict) -> list[str]:
    """Each label's success rate per world, then each pair's world-level Bonferroni p (worlds compared, min p)."""
    width = max(12, *(len(name) for name in level["per_world"]))
    lines = ["world level, exact signed-rank over the worlds paired by position (Bonferroni p, worlds compared, min p):"]
    lines += [f"{name:<{width}} success per world {rates_text(worlds)} %" for name, worlds in level["per_world"].items()]
    for rate, actions in zip(level["success_rate"]["pairs"], level["median_actions"]["pairs"]):
        lines.append(f"  {rate['a']} vs {rate['b']}: success {rank_test_text(rate)}, median actions "
                     f"{rank_test_text(actions)}")
    return lines


def all_cells(specs: list[str], records: list[dict]) -> dict[str, dict[int, dict]]:
    """LABEL -> seed -> per-seed cell: the records' (`seed_cells`) with each --cells file's seeds added (a label
    of --cells alone has the file's seeds only)."""
    cells = seed_cells(records)
    for spec in specs:
        label, _, rest = spec.partition("=")
        parts = rest.split(":")
        if not label or len(parts) not in (2, 3) or not all(parts):
            raise ConfigError(f"--cells {spec!r} is not LABEL=FILE:KEY[:VARIANT]")
        path, key, variant = Path(parts[0]), parts[1], parts[2] if len(parts) == 3 else label
        try:
            entry = json.loads(path.read_text())[key]
            held = entry.get("seed_cells", entry)["success"][variant]["seeds"]
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
            raise ConfigError(f"--cells {spec!r}: {path} holds no per-seed cells of {key}/[seed_cells/]success/"
                              f"{variant} ({type(error).__name__}: {error})")
        mine = cells.get(label, {})
        clash = sorted(set(map(int, held)) & set(mine))
        if clash:
            raise ConfigError(f"--cells {spec!r}: seeds {clash} are also in the runs or cells of {label!r}")
        cells[label] = dict(sorted({**mine, **{int(seed): cell for seed, cell in held.items()}}.items()))
    return cells


def cell_lines(level: dict) -> list[str]:
    """Each label's pooled success over every seed and per seed, then each pair's Fisher and seed-level p."""
    width = max(12, *(len(name) for name in level["success"]))
    lines = ["every seed (--cells and runs): success pooled [95 % Wilson] and per seed; Bonferroni p of Fisher's test "
             "(episodes) and of the seed-level signed-rank tests (seeds compared, min p):"]
    for name, cell in level["success"].items():
        pooled = cell["pooled"]
        low, high = pooled["ci95"]
        lines.append(f"{name:<{width}} success {100 * pooled['rate']:5.1f} % [{100 * low:.1f}, {100 * high:.1f}] "
                     f"{pooled['successes']}/{pooled['episodes']}; per seed {rates_text(cell['seeds'])} %")
    seed = level["seed_tests"]
    for fisher, rate, actions in zip(level["episode_success"]["pairs"], seed["success_rate"]["pairs"],
                                     seed["median_actions"]["pairs"]):
        lines.append(f"  {fisher['a']} vs {fisher['b']}: episodes success {p_text(fisher['p_bonferroni'])} | seeds: "
                     f"success {rank_test_text(rate)}, median actions {rank_test_text(actions)}")
    return lines


def main(argv: list[str] | None = None) -> int:
    """Pool, write and print; bad input (a malformed --run or --cells, a folder without episodes, runs that
    disagree) gives one line on stderr and exit status 2, and writes nothing."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", action="append", required=True,
                        help="LABEL=DIR[&DIR...][+DIR[&DIR...]...][:VARIANT][@SEEDS]: & joins runs of different "
                             "seeds, + worlds")
    parser.add_argument("--out", type=Path, required=True, help="JSON file to write (KEY added if it exists)")
    parser.add_argument("--key", default="pooled", help="the entry of --out to write (default pooled)")
    parser.add_argument("--damage", help="only the damages whose label fully matches this regular expression")
    parser.add_argument("--summary", type=Path, help="also write `evaluation.summarise` of the episodes here")
    parser.add_argument("--figure", type=Path, help="also draw Fig. 6 (the paper's method) of the episodes here")
    parser.add_argument("--max-actions", type=int, default=80, help="the runs' action cap (default 80, maze_eval's)")
    parser.add_argument("--cells", action="append", default=[],
                        help="LABEL=FILE:KEY[:VARIANT]: LABEL's per-seed cells of other seeds from a statistics file")
    args = parser.parse_args(argv)
    try:
        return pool(args)
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2


def pool(args: argparse.Namespace) -> int:
    """What main does with its arguments; ConfigError for bad input, before anything is written."""
    runs = [pooled(spec, args.damage) for spec in args.run]
    worlds = {count for _, count in runs}
    if len(worlds) > 1:
        raise ConfigError("the runs pool different numbers of folders (worlds): "
                          + ", ".join(f"{spec.partition('=')[0]!r} {count}" for spec, (_, count) in zip(args.run, runs)))
    records = [r for run, _ in runs for r in run]
    cells = all_cells(args.cells, records) if args.cells else None
    stats = protocol_statistics(records)
    if args.figure:
        plot_protocol_box(args.figure, stats, args.max_actions)
    stats.pop("medians")
    if worlds != {1}:
        stats["world_level"] = world_level(records)
    if cells is not None:
        stats["seed_cells"] = cell_statistics(cells)
    data = json.loads(args.out.read_text()) if args.out.is_file() else {}
    data[args.key] = stats
    args.out.write_text(json.dumps(data, indent=1) + "\n")
    if args.summary:
        args.summary.write_text(json.dumps(summarise(records, args.max_actions), indent=1) + "\n")
    print(PAPER_METHOD_HEADER)
    for name, v in stats["variants"].items():
        print(f"{name:24s} p25/p50/p75 {v['p25']:5.1f} {v['p50']:5.1f} {v['p75']:5.1f}  failed {v['failure_percent']:5.1f} %"
              f"  ({v['replications']} replications, {v['episodes']} episodes)")
    print("\n".join(level_lines(stats) + (world_lines(stats["world_level"]) if "world_level" in stats else [])
                    + (cell_lines(stats["seed_cells"]) if "seed_cells" in stats else [])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
