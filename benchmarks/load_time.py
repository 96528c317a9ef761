"""How long does loading a repertoire take? `load_hbr` (and `load_spare`) look up every middle
elite's 6 leg controllers in the bottom layer (`hbr.middle.elite_controllers`), the bulk of a
`maze_eval` start-up before any compilation.

Per repeat, in a fresh subprocess (no cache of an earlier load): the wall time of `load_hbr` on the
HBR file, of `load_spare` on the spare archive beside it (if any), and with --whole the same lookup
done the old way, over every middle slot against every bottom cell, checked equal bit for bit.

    python benchmarks/load_time.py                          # the shipped HBR, 3 repeats
    python benchmarks/load_time.py --hbr runs/hbr-gpu/hbr.npz --whole --repeats 5

Prints a table (medians) and writes JSON to benchmarks/results/.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from common import environment, result_path, run_worker


def _parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hbr", default=None, help="HBR file (default: the shipped one)")
    p.add_argument("--repeats", type=int, default=3, help="fresh processes timed (median reported)")
    p.add_argument("--whole", action="store_true", help="also time the whole-capacity lookup and compare")
    p.add_argument("--timeout", type=float, default=600.0, help="seconds allowed per repeat")
    p.add_argument("--out", type=Path, default=None, help="JSON path (default: results/load_time_<device>_<date>.json)")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def _worker(args) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from hte_jax.hbr.middle import decode, leg_controllers
    from hte_jax.hbr.store import load_hbr, load_spare, spare_beside

    row = {}
    tick = time.perf_counter()
    hbr, _, _ = load_hbr(args.hbr)
    jax.block_until_ready(hbr.middle_params)
    row["load_hbr_s"] = time.perf_counter() - tick
    row["middle_filled"] = int(np.asarray(hbr.middle.filled).sum())
    row["middle_capacity"] = int(hbr.middle.filled.shape[0])
    row["bottom_filled"] = int(np.asarray(hbr.bottom.filled).sum())
    row["bottom_capacity"] = int(hbr.bottom.filled.shape[0])
    spare = spare_beside(args.hbr)
    if spare is not None:
        tick = time.perf_counter()
        jax.block_until_ready(load_spare(spare, hbr).middle_params)
        row["load_spare_s"] = time.perf_counter() - tick
    if args.whole:
        tick = time.perf_counter()
        whole = jnp.where(hbr.middle.filled[:, None], leg_controllers(hbr.bottom, decode(hbr.middle.genotypes)), 0.0)
        whole = np.asarray(jax.block_until_ready(whole))
        row["whole_lookup_s"] = time.perf_counter() - tick
        row["whole_equal"] = bool(np.array_equal(whole, np.asarray(hbr.middle_params)))
    return row


def main(argv=None):
    args = _parse(argv)
    if args.worker:
        print(json.dumps(_worker(args)))
        return
    env = environment()
    cmd = [sys.executable, __file__, "--worker"] + (["--hbr", args.hbr] if args.hbr else []) + (["--whole"] if args.whole else [])
    rows = []
    for k in range(args.repeats):
        rows.append(run_worker(cmd, args.timeout, {"repeat": k}))
        print(json.dumps(rows[-1]), flush=True)
    good = [r for r in rows if "error" not in r]
    if not good:
        raise SystemExit(f"every repeat failed: {rows[0]['error']}")
    medians = {key: statistics.median(r[key] for r in good) for key in good[0] if key.endswith("_s")}
    print(f"\n{'measure':<16} {'median s':>9}  ({len(good)} runs; middle {good[0]['middle_filled']} of "
          f"{good[0]['middle_capacity']} slots, bottom {good[0]['bottom_filled']} of {good[0]['bottom_capacity']})")
    for key, value in medians.items():
        print(f"{key.removesuffix('_s'):<16} {value:>9.2f}")
    if "whole_equal" in good[0]:
        print(f"whole lookup equal bit for bit: {all(r['whole_equal'] for r in good)}")
    out = args.out or result_path("load_time", env)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"environment": env, "settings": vars(args) | {"out": str(out)}, "rows": rows,
                               "medians": medians}, indent=2, default=str) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
