"""Pool the held-out suite's episodes per damage set (how statistics_{locked,removed}.json were made).

    python benchmarks/results/heldout_suite_h200x2_2026-11-28/pool_heldout.py RECORDS.json OUTDIR

RECORDS.json (not committed: raw episodes) maps each run folder (random0 .. random7) to its finished batch
files (episodes_<k>.npz) and each file's metadata (`read_checkpoint(path)[1]["metadata"]`, whose "records"
are maze_eval's episode records). Per set (the paper's seven damages locked; the same seven removed):
* the paper's method and the episode level (`protocol_statistics`): one repertoire seed, each episode its own
  replication (replicate = 3 K + r for maze random:K, replicate r), so a replication median is the episode's value;
  the seed-level tests have one seed and can say nothing (p = 1, min_p = 1);
* "maze_level": `seed_level_tests` with the maze index K as the unit (8 mazes paired by maze; min p 2/2^8);
* "random1_with_2d-rte": random:1 alone with 2D-RTE, the one maze whose 2D-RTE batch finished.
`summary_<set>.json` is `evaluation.summarise` of the pooled HBR variants' records (per variant and damage).
"""
import json
import sys
from pathlib import Path

from hte_jax.online.evaluation import summarise
from hte_jax.online.plots import plot_protocol_box
from hte_jax.online.statistics import (PAPER_METHOD_HEADER, level_lines, protocol_statistics, seed_level_tests,
                                       success_rates)

REPLICATES = 3
SETS = {"locked": lambda d: ":" not in d, "removed": lambda d: d.endswith(":removed")}
ORDER = ["hte-spare", "perfect-spare", "perfect-hte", "hte", "rte", "2d-rte", "aprol"]
MAZE_SAMPLE = ("maze level: the generated maze (random:0..7) as the unit, each variant's value per maze (all 7 "
               "damages) compared over the 8 mazes, paired by maze; exact two-sided Wilcoxon signed-rank "
               "(`seed_level_tests` with the maze index in place of the seed), Bonferroni over the pairs; one "
               "repertoire seed throughout")


def main(src: str, outdir: str) -> None:
    data, out = json.loads(Path(src).read_text()), Path(outdir)
    for name, keep in SETS.items():
        recs, by_maze = [], []
        for maze, files in sorted(data.items()):
            k = int(maze.removeprefix("random"))
            for _, meta in sorted(files.items()):
                for r in meta["records"]:
                    if keep(r["damage"]):
                        r = {key: v for key, v in r.items() if key != "prediction_error"}
                        recs.append({**r, "replicate": REPLICATES * k + r["replicate"], "seed": 0, "maze": k})
                        by_maze.append({**r, "seed": k})
        recs.sort(key=lambda r: ORDER.index(r["variant"]))
        by_maze.sort(key=lambda r: ORDER.index(r["variant"]))
        hbr = [r for r in recs if r["variant"] != "2d-rte"]
        hbr_maze = [r for r in by_maze if r["variant"] != "2d-rte"]
        stats = protocol_statistics(hbr)
        plot_protocol_box(out / f"fig6_actions_{name}.png", stats, 80)
        stats.pop("medians")
        stats["maze_level"] = {"sample": MAZE_SAMPLE,
                               "per_maze": {v: c["seeds"] for v, c in success_rates(hbr_maze).items()},
                               **{q: seed_level_tests(hbr_maze, q) for q in ("success_rate", "median_actions")}}
        stats["random1_with_2d-rte"] = {
            "note": "random:1 alone (21 episodes per variant), the one maze whose 2D-RTE batch finished",
            "success": success_rates([r for r in recs if r["maze"] == 1])}
        (out / f"statistics_{name}.json").write_text(json.dumps(stats, indent=1) + "\n")
        (out / f"summary_{name}.json").write_text(json.dumps(summarise(hbr, 80), indent=1) + "\n")
        print(f"== {name}: {len(hbr)} episodes of the HBR variants (8 mazes x 7 damages x {REPLICATES})")
        print(PAPER_METHOD_HEADER)
        for v, s in stats["variants"].items():
            print(f"{v:14s} {s['p25']:.0f} / {s['p50']:.0f} / {s['p75']:.0f}  failed {s['failure_percent']:.1f} %")
        print("\n".join(level_lines(stats)))


if __name__ == "__main__":
    main(*sys.argv[1:3])
