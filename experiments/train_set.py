"""Train one repertoire seed's whole set into a seed folder that `maze_eval --repertoire-dir` reads.

    python -m experiments.train_set --seed 1 --preset gpu --out runs/seeds/seed1
    python -m experiments.train_set --seed 1 --preset gpu --out runs/seeds/seed1 --impl warp --matched
    python -m experiments.train_set --seed 1 --preset gpu --out runs/seeds/seed1 --resume   # after a kill
    python -m experiments.train_set --seed 1 --preset gpu --out runs/seeds/seed1 --resume --parts aprol
    python -m experiments.maze_eval --protocol hte-jax --preset gpu --repertoire-dir runs/seeds

Trains, each in a run folder under --out/runs: the HBR, its spare archive, Flat-2D, Flat-8D, APROL's
21 (always impl jax), and with --matched a Flat-2D with the HBR's plus the spare archive's evaluations.
Writes hbr.npz, spare.npz, flat2d.npz, flat8d.npz, aprol.npz (matched/flat2d.npz) and set.json (per
part: evaluations, elites, wall time) under --out. --resume keeps finished parts and resumes the one
it was in; --parts trains some parts only (two processes may train two parts of a set). Bad values
give a one-line error and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import jax

from experiments.cli import (add_device_flags, device_mesh, input_errors, interruptible, is_writer, resume_command,
                             show_progress)
from hte_jax.config import with_overrides
from hte_jax.errors import ConfigError
from hte_jax.flat import training as flat
from hte_jax.hbr import training as hbr_training
from hte_jax.hbr.store import SPARE_FILE, load_hbr
from hte_jax.qd.io import write_json

FLAT_FILES = {"2d": "flat2d.npz", "8d": "flat8d.npz", "aprol": "aprol.npz"}  # the names maze_eval reads
PARTS = ("hbr", "spare", "2d", "8d", "aprol", "matched")
MATCHED = Path("matched") / FLAT_FILES["2d"]


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, required=True, help="the set's seed (the shipped set is seed 0)")
    p.add_argument("--out", required=True, help="the seed folder")
    p.add_argument("--preset", default="cpu", help=f"one of {', '.join(hbr_training.PRESETS)} (default cpu)")
    p.add_argument("--impl", default="jax", help="MJX implementation, jax or warp (APROL's 21 always jax)")
    p.add_argument("--matched", action="store_true", help="also a Flat-2D with the HBR + spare archive's budget")
    p.add_argument("--parts", default=None, help=f"only these parts, comma-separated, of {', '.join(PARTS)}")
    p.add_argument("--resume", action="store_true", help="continue the set in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_device_flags(p)
    return p


def _saved(out: Path) -> str | None:
    done = ", ".join(part for part in PARTS if _final(out, part).is_file()) or "none"
    return f"finished parts {done} in {out}, the current part's checkpoint" if out.is_dir() else None


def _final(out: Path, part: str) -> Path:
    """Where a part's repertoire file lands in the seed folder."""
    return out / {"hbr": "hbr.npz", "spare": SPARE_FILE, "matched": str(MATCHED)}.get(part, FLAT_FILES.get(part, ""))


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    with interruptible(lambda: _saved(Path(args.out)), resume_command("experiments.train_set", argv, args.out)):
        with input_errors() as errors:
            mesh = device_mesh(args)
            out = Path(args.out)
            parts = _parts(args.parts, args.matched)
            if out.exists() and any(out.iterdir()) and not args.resume:
                raise ConfigError(f"{out} is not empty: pass --resume to continue the set there, or another --out")
            if args.resume and not out.is_dir():
                raise ConfigError(f"--resume: {out} holds no set to resume")
            if args.impl not in ("jax", "warp"):
                raise ConfigError(f"--impl must be jax or warp, got {args.impl!r}")
            hbr_config = with_overrides(hbr_training.preset(args.preset), {"seed": args.seed, "solver.impl": args.impl})
            for part in parts:
                if _final(out, part).is_file():
                    continue
                run_dir = out / "runs" / part
                resume, progress, began = (run_dir / "config.json").is_file(), show_progress(args), time.perf_counter()
                impl = "jax" if part == "aprol" else args.impl
                if part == "hbr":
                    summary = hbr_training.train_hbr(hbr_config, run_dir, resume_run=resume, progress=progress,
                                                     mesh=mesh).summary
                    record = {"evaluations": sum(s["evaluations"] for s in summary["layers"].values()),
                              "elites": {k: s["filled"] for k, s in summary["layers"].items()},
                              "statistics": summary["statistics"]}
                elif part == "spare":
                    if not _final(out, "hbr").is_file():
                        raise ConfigError(f"the spare archive needs {_final(out, 'hbr')}: train part hbr first")
                    hbr, _, _ = load_hbr(_final(out, "hbr"))
                    summary = hbr_training.train_spare(hbr, hbr_config, run_dir, resume_run=resume, progress=progress)
                    record = {k: summary[k] for k in ("evaluations", "elites", "patterns", "lifting_each_leg")}
                else:
                    config = with_overrides(flat.preset(args.preset, "2d" if part == "matched" else part),
                                            {"seed": args.seed, "solver.impl": impl})
                    if part == "matched":
                        config = with_overrides(config, {"generations": _matched_generations(out, config)})
                    summary = flat.train_flat(config, run_dir, resume_run=resume, progress=progress, mesh=mesh).summary
                    record = {k: summary[k] for k in ("evaluations", "elites", "statistics")}
                if not is_writer():
                    continue
                produced = run_dir / {"hbr": "hbr.npz", "spare": SPARE_FILE}.get(part, "repertoires.npz")
                write_json(run_dir / "part.json",
                           {**record, "impl": impl, "wall_time_s": round(time.perf_counter() - began, 1)})
                _final(out, part).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(produced, _final(out, part))
                records = {p: _record(out, p) for p in PARTS if (out / "runs" / p / "part.json").is_file()}
                write_json(out / "set.json", {"seed": args.seed, "preset": args.preset,
                                              "devices": [str(d) for d in jax.devices()], "parts": records})
                print(f"{out}: {part} done, {record['evaluations']} evaluations")
        return 2 if errors.failed else 0


def _parts(text: str | None, matched: bool) -> list[str]:
    """The parts asked for, in training order."""
    asked = PARTS[:-1] + (("matched",) if matched else ()) if text is None else tuple(text.split(","))
    unknown = [p for p in asked if p not in PARTS]
    if unknown:
        raise ConfigError(f"unknown part(s) {', '.join(unknown)}; choose among {', '.join(PARTS)}")
    return [p for p in PARTS if p in asked]


def _record(out: Path, part: str) -> dict:
    return json.loads((out / "runs" / part / "part.json").read_text())


def _matched_generations(out: Path, config) -> int:
    """Generations that give a Flat-2D the evaluations of this set's HBR plus its spare archive."""
    missing = [p for p in ("hbr", "spare") if not (out / "runs" / p / "part.json").is_file()]
    if missing:
        raise ConfigError(f"the matched Flat-2D needs the evaluations of part(s) {', '.join(missing)}: train them first")
    budget = _record(out, "hbr")["evaluations"] + _record(out, "spare")["evaluations"]
    return -(-(budget - config.init_size) // config.batch_size)


if __name__ == "__main__":
    sys.exit(main())
