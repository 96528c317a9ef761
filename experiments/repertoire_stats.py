"""Table 2 of the paper: repertoire size, effective x-y size and projected mean fitness, over seeds.

    python -m experiments.repertoire_stats          # the shipped HBR and flat repertoires (assets/): 14 s
    python -m experiments.repertoire_stats --hbr runs/hbr-s0 runs/hbr-s1 runs/hbr-s2 \
        --flat8d runs/f8-s0 runs/f8-s1 runs/f8-s2 --flat2d runs/f2-s0 --out runs/table2

Each path is a repertoire file or a training run folder. Prints our numbers beside the paper's
and writes table2.json (every file's row and the aggregate) and table2.md under --out.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from experiments.cli import input_errors, interruptible
from hte_jax.errors import ConfigError
from hte_jax.flat.comparison import aggregate, file_statistics, markdown_table
from hte_jax.flat.store import shipped_flat_path
from hte_jax.hbr.store import shipped_hbr_path
from hte_jax.qd.io import write_json


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hbr", nargs="*", default=None, help="HBR files or run folders (default: shipped)")
    p.add_argument("--flat8d", nargs="*", default=None, help="8-D flat files or run folders (default: shipped)")
    p.add_argument("--flat2d", nargs="*", default=None, help="2-D flat files or run folders (default: shipped)")
    p.add_argument("--out", default="runs/repertoire_stats", help="folder for table2.json and table2.md")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    with interruptible() as interrupt:
        if any(x is not None for x in (args.hbr, args.flat8d, args.flat2d)):
            paths = [*(args.hbr or []), *(args.flat8d or []), *(args.flat2d or [])]
        else:
            paths = [shipped_hbr_path(), shipped_flat_path("8d"), shipped_flat_path("2d")]
        with input_errors() as errors:
            if not paths:
                raise ConfigError("no repertoire given")
            rows = [file_statistics(path) for path in paths]
        if errors.failed:
            return 2
        table = aggregate(rows)
        print(text := markdown_table(table), end="")
        out = Path(args.out)
        interrupt.saved = f"part of table2.json and table2.md written in {out}"
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "table2.json", {"rows": rows, "aggregate": table})
        (out / "table2.md").write_text(text)
        print(f"wrote {out / 'table2.json'} and {out / 'table2.md'}")
        return 0


if __name__ == "__main__":
    sys.exit(main())
