"""Damage recovery in the maze: RTE / HTE variants adapt online, reset-free, many episodes per batch.

    python -m experiments.maze_eval                                  # HTE, 7 damages, cpu preset: 154 s on 2 cores
    python -m experiments.maze_eval --variant hte,perfect-hte,rte --damage leg1 --replicates 3
    python -m experiments.maze_eval --variant 2d-rte,8d-rte          # RTE on the shipped flat repertoires
    python -m experiments.maze_eval --preset gpu --variant hte,perfect-hte,random-hte,rte
    python -m experiments.maze_eval --repertoire runs/hbr-gpu/hbr.npz --damage none,0,6
    python -m experiments.maze_eval --protocol paper --preset gpu    # the paper's Fig. 6 / 7 experiment
    python -m experiments.maze_eval --protocol paper --damage-model locked
    python -m experiments.maze_eval --damage leg0:removed,leg2:shortened=0.5:friction=0.6,none:friction=0.5
    python -m experiments.maze_eval --damage suite --damage-model removed   # the held-out damage suite
    python -m experiments.maze_eval --protocol hte-jax --preset gpu  # our HTE (hte-spare) against RTE and 2D-RTE
    python -m experiments.maze_eval --protocol ablations --preset gpu --maze random:3 --damage suite  # what pays
    python -m experiments.maze_eval --protocol paper --preset gpu --repertoire-dir runs/seeds  # R seeds
    python -m experiments.maze_eval --protocol paper --preset gpu --repertoire-dir runs/seeds --resume  # after a kill
    python -m experiments.maze_eval --protocol paper --preset gpu --repertoire-dir runs/seeds --spread batches  # a process per GPU
    python -m experiments.maze_eval --protocol paper --preset gpu --repertoire-dir runs/seeds --seeds 1,2,3 --impl warp
    python -m experiments.maze_eval --variant hte --damage leg1 --video 1   # and a video of the episode
    python -m experiments.maze_eval --maze two_rooms --variant hte,rte   # another world (assets/mazes/ or a JSON file)
    python -m experiments.maze_eval --maze random:3 --variant hte,rte    # the generated maze of seed 3 (K >= 0)
    python -m experiments.maze_eval --set planner.iterations=50 --set solver.ls_iterations=8  # dotted keys

Variants: hte, perfect-hte, random-hte, rte (on an HBR: the shipped one or --repertoire; rte also on a
flat file), 2d-rte, 8d-rte, aprol (shipped flat repertoires). --protocol paper: the paper's six variants
on all 7 damages; hte-jax: hte-spare, perfect-spare, perfect-hte, hte, rte, 2d-rte on all 7 with
--reflex-tilt 0.3 --reflex-release 0.15 (docs/results.md).

--damage: all (the paper's 7) or comma-separated items <legs>[:<model>[=<fraction>]][:friction=<scale>]:
  <legs>        none, leg0..leg5 (= 0..5), legs1+4 (= 6), legs<i>+<j>(+<k>...) increasing, -1 (none),
                or all (the paper's 7, each with the rest of the item)
  <model>       raised, locked, removed (no fraction); shortened=<f> (the tibia at f of its length),
                weak=<f> (the servos at f of their torque), f in (0, 1]; default: --damage-model
  friction=<s>  the floor's friction x s (> 0; default 1)
e.g. leg0:removed, leg2:shortened=0.5:friction=0.6, none:friction=0.5 (the intact robot on a slippery
floor), all:locked. --damage-model: the model of the items that name none: raised (default, the leg
blocked in the air), locked (in its standing pose) or removed. Each damage is named in the outputs by
its canonical label (the model omitted where it is --damage-model, the friction where it is 1).
--repertoire-dir: a subfolder per seed with hbr.npz, flat2d.npz, flat8d.npz, aprol.npz
(from `experiments.train_set`); a replication's score is the median over seeds. --seeds 1,2,3 runs only
those seeds (indices of the subfolders in name order), each keeping its index and its episodes
(benchmarks/pool_statistics.py --run "LABEL=DIR&DIR" pools such runs). --resume reads the
batches a killed run finished and runs the others: the results equal an uninterrupted run's.
A seed's batches (its HBR variants, each flat repertoire) run together: each action plans all of them in one
search, then acts all of them in one program (--together none: one batch after another; the same results up to
float rounding). --spread batches starts a worker process per device (each on that device alone, running the
batches dealt to it, a seed's together, into their episodes_<k>.npz), waits for them, then summarises the batch
files as --resume does.

Writes config.json, episodes.json, summary.json (per variant and damage), statistics.json (the
paper's method: quartiles of the replication medians, failure rates, Wilcoxon-Mann-Whitney tests with
Bonferroni correction; episode level: success rates with 95 % Wilson intervals pooled, per damage and
per seed, Fisher and Mann-Whitney tests; seed level: exact signed-rank tests over the seeds),
episodes_<k>.npz (trajectories, plans, patterns of batch k) and plots/ under --out (default
runs/maze-eval). --video N records the first N episodes of each variant (no result changes) as
replays/<variant>_ep<I>.npz and renders videos/<variant>_ep<I>_<damage>.mp4 with `experiments.render
episode`; where no OpenGL backend starts, one line says what to install and how to render them later.
Bad values give a one-line error and exit status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from jax.sharding import Mesh
from tqdm.auto import tqdm

from experiments import batch_workers
from experiments.cli import (EXIT_INTERRUPTED, add_device_flags, add_setting_flags,
                             device_mesh, input_errors, interruptible, is_writer, resumable_run, resume_command,
                             setting_overrides, show_progress)
from hte_jax import sharding
from hte_jax.config import settings
from hte_jax.errors import ConfigError, require_int
from hte_jax.online.evaluation import (PRESETS, PROTOCOLS, EvalConfig, batch_labels, batches, episode_numbers,
                                      episode_records, prediction_errors, preset, protocol_overrides, rows_to_record,
                                      run_batches, summarise, with_overrides)
from hte_jax.online.plots import (episode_track, plot_episodes, plot_failures, plot_prediction_error, plot_protocol_box,
                                  plot_variant_mazes)
from hte_jax.online.recording import replay_path, save_replay
from hte_jax.online.statistics import (PAPER_FAILURE_REDUCTION, PAPER_METHOD_HEADER, PAPER_QUARTILES, failure_reduction,
                                       failure_reductions, level_lines, protocol_statistics)
from hte_jax.qd.io import prepare_run_dir, read_checkpoint, save_checkpoint, write_json
from hte_jax.sim.damage import DAMAGE_PARTS
from hte_jax.sim.mjx_import import require_impl
from hte_jax.viz import gl

SETTINGS = list(settings(EvalConfig))  # override keys, inlined settings (the planner's, the solver's) by their names
SPREADS = ("episodes", "batches")  # --spread: what several devices split
TOGETHER = ("seed", "none")  # --together: which batches run together
RECORD_EVERY = 4  # control steps between the recorded states of --video episodes (25 per simulated second)
ROOT = Path(__file__).resolve().parents[1]


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="cpu", help=f"one of {', '.join(PRESETS)} (default cpu)")
    p.add_argument("--protocol", default=None, help=f"one of {', '.join(PROTOCOLS)}: its variants on every damage (hte-jax: "
                   "ours against the baselines, with the tilt reflex; ablations: each half of hte-spare beside it); other "
                   "flags override it")
    p.add_argument("--out", default="runs/maze-eval", help="output folder (default runs/maze-eval)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out: its finished batches (episodes_<k>.npz) are read, not run again")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--spread", default="episodes", metavar="WHAT",
                   help="with several devices: 'episodes' (default) splits each batch's episodes over them, one batch "
                        "after another; 'batches' starts a worker process per device, each running whole batches "
                        "dealt in turn (under --together seed a seed's batches to one worker; the planner's host "
                        "round trips overlap), then summarises their batch files as --resume does (not with "
                        "--distributed)")
    p.add_argument("--together", default="seed", metavar="WHICH",
                   help="'seed' (default): the batches of a seed (its HBR variants, each flat repertoire) run together, "
                        "each action planning all of them in one search and acting all of them in one program; 'none': "
                        "one batch after another (the same results up to float rounding)")
    # K,K,...: the batches a worker process of --spread batches runs (with --resume), and no summary
    p.add_argument("--worker-batches", default=None, help=argparse.SUPPRESS)
    p.add_argument("--show-config", action="store_true", help="print the resolved configuration and exit")
    p.add_argument("--video", default="0", metavar="N",
                   help="record the first N episodes of each variant and write their videos (default 0: none)")
    add_device_flags(p)
    add_setting_flags(p, dict.fromkeys(SETTINGS, "V"), {"variants": "--variant", "damages": "--damage"})
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    argv = sys.argv[1:] if argv is None else list(argv)
    with interruptible() as interrupt:
        with input_errors() as errors:
            share = _worker_batches(args.worker_batches, args.resume)  # None: this process runs the run's batches
            worker_env = dict(os.environ)  # before this process's GPU setting below
            with batch_workers.gpu_memory_left_free(args.spread == "batches" and share is None and args.devices != 1):
                mesh = device_mesh(args)  # first: --distributed must start before jax touches the devices
            workers = _worker_devices(args.spread, mesh, args.distributed, share)
            writer = is_writer()  # only process 0 of a multi-host run writes files
            overrides = protocol_overrides(args.protocol) if args.protocol is not None else {}
            overrides.update(setting_overrides(args, SETTINGS))
            config = with_overrides(preset(args.preset), overrides)
            videos = _video_count(args.video)
            if args.show_config:
                print(json.dumps(config.to_dict(), indent=2))
                return 0
            if args.together not in TOGETHER:
                raise ConfigError(f"--together must be one of {', '.join(TOGETHER)}, got {args.together!r}")
            require_impl(config.robot.impl)  # its backend, here
            if not workers:
                _check_warp_spread(config.robot.impl, mesh)
            planned = batches(config)  # before anything is written: reads the seed folders
            if share is not None:
                _check_batch_indices(share, len(planned))
            out = Path(args.out)
            stored = {"preset": args.preset, "protocol": args.protocol, **config.to_dict()}
            if args.resume:
                resumable_run(out, ())  # ConfigError unless out holds a run
                prepare_run_dir(out, stored, resume_run=True)  # ConfigError unless it is this run
            elif writer:
                out.mkdir(parents=True, exist_ok=True)
                for old in out.glob("episodes_*.npz"):  # an earlier run's batches: this run replaces them
                    old.unlink()
                write_json(out / "config.json", stored)
            interrupt.saved = f"wrote {out / 'config.json'} only"
            interrupt.resume = resume_command("experiments.maze_eval", argv, out)
            maze = config.maze_task  # read once for every batch and plot
            records, curves, tracks = [], {}, {}
            earlier, recorded = {}, []  # episodes of each variant in earlier batches; (variant, episode) recorded
            plans = []
            for seed, path, variants in planned:
                labels = [v for v, _, _ in batch_labels(config, variants)]
                plans.append((labels, rows_to_record(labels, videos, earlier), episode_numbers(labels, earlier)))
                earlier = {v: earlier.get(v, 0) + labels.count(v) for v in {*earlier, *labels}}

            def run(ks: list[int]) -> dict:
                """Batches ks (of one seed) run together, their replays and batch files written: k -> (result,
                rows, recorded)."""
                seed = planned[ks[0]][0]
                results = run_batches(config, [planned[k][1:] for k in ks], maze, progress=show_progress(args),
                                      seed=seed, record=[plans[k][1] for k in ks], record_every=RECORD_EVERY,
                                      mesh=mesh)
                ran = {}
                for k, result in zip(ks, results):
                    rows = episode_records(result, config.max_actions)
                    if not writer:
                        ran[k] = (result, rows, [])
                        continue
                    # the replays before the batch file: a batch that is read has its replays
                    saved = _save_replays(out, result, plans[k][2], k)
                    _save_batch(out / f"episodes_{k}.npz", result, rows, ks)
                    ran[k] = (result, rows, saved)
                return ran

            done = [args.resume and (out / f"episodes_{k}.npz").is_file() for k in range(len(planned))]
            if share is not None:  # a worker of --spread batches: its batches' files, no summary
                interrupt.saved = lambda: _batches_written(out, len(planned))
                for i, unit in enumerate(_units(args.together, planned, [k for k in share if not done[k]])):
                    if i and batch_workers.parent_gone():
                        print(f"stopped before batch {unit[0]}: the process that started this worker stopped or "
                              "asked it to", file=sys.stderr)
                        return EXIT_INTERRUPTED
                    for k, (result, rows, _) in run(unit).items():
                        print(_batch_line(k, planned[k], result, rows), flush=True)
                return 0
            by_workers = [k for k in range(len(planned)) if not done[k]] if workers else []
            if by_workers:
                interrupt.saved = lambda: _batches_written(out, len(planned))
                processes = batch_workers.plan_workers("experiments.maze_eval", workers,
                                                       _units(args.together, planned, by_workers), argv, worker_env)
                try:
                    batch_workers.run_workers(processes, out, show_progress(args), interrupt)
                except batch_workers.WorkerFailed as failure:
                    print(f"error: {failure}; resume with: {interrupt.resume}", file=sys.stderr)
                    return failure.status
                done = [True] * len(planned)
            pending = {}  # batches run together with an earlier one, not yet reported
            units = _units(args.together, planned, [k for k in range(len(planned)) if not done[k]])
            for k, (seed, path, variants) in enumerate(planned):
                labels, to_record, numbers = plans[k]
                batch_file = out / f"episodes_{k}.npz"
                if done[k]:
                    result, rows = _load_batch(batch_file, seed, batch_labels(config, variants))
                    records += rows
                    recorded += [(labels[row], numbers[row]) for row in to_record]
                    if writer:
                        _plot_batch(out / "plots", result, curves, tracks, maze, planned[0][0])
                        if k not in by_workers:  # a worker printed the line of each batch it ran
                            print(f"batch {k} ({'/'.join(variants)} on seed {seed}): read from {batch_file}")
                    continue
                if k not in pending:  # this batch and the others of its unit (its seed's, under --together seed)
                    pending = run(next(u for u in units if k in u))
                result, rows, saved = pending.pop(k)
                records += rows
                if not writer:
                    continue
                recorded += saved
                interrupt.saved = f"wrote {_batch_files(k + 1, len(planned))} in {out}, no summary"
                _plot_batch(out / "plots", result, curves, tracks, maze, planned[0][0])
                print(_batch_line(k, planned[k], result, rows))
        if errors.failed:
            return 2
        if not writer:
            return 0
        interrupt.saved = f"wrote {_batch_files(len(planned), len(planned))} in {out}, part of the summaries, plots, videos"
        order = {name: i for i, name in enumerate(config.variant_list)}
        records.sort(key=lambda r: order[r["variant"]])  # stable: the variants in the order asked for
        summary = summarise(records, config.max_actions)
        statistics = protocol_statistics(records)
        variant, baseline, paper_reduction = PAPER_FAILURE_REDUCTION
        if variant in statistics["variants"] and baseline in statistics["variants"]:
            statistics["failure_reduction"] = {"variant": variant, "baseline": baseline, "paper_percent": paper_reduction,
                                               "percent": failure_reduction(statistics, variant, baseline)}
        if baseline in statistics["variants"] and len(statistics["variants"]) > 1:
            statistics["failure_reductions"] = {"baseline": baseline, "percent": failure_reductions(statistics, baseline)}
        write_json(out / "episodes.json", {"episodes": records})
        write_json(out / "summary.json", summary)
        write_json(out / "statistics.json", statistics)
        plot_prediction_error(out / "plots" / "prediction_error.png", curves)
        plot_protocol_box(out / "plots" / "fig6_actions.png", statistics, config.max_actions, PAPER_QUARTILES)
        plot_failures(out / "plots" / "fig7_failures.png", statistics)
        plot_variant_mazes(out / "plots" / "maze_variants.png", maze, tracks)
        unrendered = _write_videos(out, recorded, progress=not args.no_progress)
        width = max(8, *(len(r["damage"]) for r in records))
        print(f"{'variant':<12} {'damage':<{width}} {'rep':>3} {'actions':>7}  result")
        for r in records:
            result = "goal" if r["reached"] else ("flipped" if r["broken"] else "failed")
            print(f"{r['variant']:<12} {r['damage']:<{width}} {r['replicate']:>3} {r['actions']:>7}  {result}")
        _print_statistics(statistics)
        if unrendered:  # the results are written: the run succeeded without its videos
            print(unrendered, file=sys.stderr)
        print(f"wrote {out}")
        return 0


def _batch_line(k: int, batch: tuple, result, rows: list[dict]) -> str:
    """The line a batch run prints: its variants, seed, repertoire, episodes and times."""
    seed, _, variants = batch
    return (f"batch {k} ({'/'.join(variants)} on seed {seed}: {result.repertoire['path']}, "
            f"{result.repertoire['actions']} actions): {len(rows)} episodes in {result.timings.total:.1f} s, "
            f"planning median {np.median(result.timings.plan):.2f} s per action")


def _units(which: str, planned: list, todo: list[int]) -> list[list[int]]:
    """The batches `todo` in the groups that run together, in order: under --together seed those of a seed."""
    if which == "none":
        return [[k] for k in todo]
    seeds = {}
    for k in todo:
        seeds.setdefault(planned[k][0], []).append(k)
    return list(seeds.values())


def _worker_batches(text: str | None, resume: bool) -> list[int] | None:
    """The batches --worker-batches K,K,... names (a --spread batches worker's), in order; None when not given."""
    if text is None:
        return None
    items = [item.strip() for item in text.split(",")]
    if not all(item.isdecimal() for item in items):
        raise ConfigError(f"--worker-batches must be comma-separated batch indices (integers >= 0), got {text!r}")
    indices = [int(item) for item in items]
    if len(set(indices)) < len(indices):
        raise ConfigError(f"--worker-batches names a batch twice: {text!r}")
    if not resume:
        raise ConfigError("--worker-batches runs batches of a started run: give --resume too")
    return indices


def _check_batch_indices(indices: list[int], count: int) -> None:
    """ConfigError unless every batch of --worker-batches is one of the run's `count` batches."""
    outside = [k for k in indices if k >= count]
    if outside:
        raise ConfigError(f"--worker-batches: this run has batches 0 to {count - 1}, not {outside[0]}")


def _worker_devices(spread: str, mesh: Mesh, distributed: bool, share: list[int] | None) -> list:
    """The devices that each get a worker process: the mesh's under --spread batches with several devices;
    none where this process runs the batches itself (over the whole mesh)."""
    if spread not in SPREADS:
        raise ConfigError(f"--spread must be one of {', '.join(SPREADS)}, got {spread!r}")
    if spread == "episodes" or share is not None:
        return []
    if distributed:
        raise ConfigError("--spread batches starts a process per device itself: leave out --distributed, or spread "
                          "episodes")
    devices = list(mesh.devices.flat)
    others = sorted({d.platform for d in devices} - {"cpu", "gpu"})
    if others:
        raise ConfigError(f"--spread batches runs a process per GPU or CPU device, not on {others[0]} devices: spread "
                          "episodes")
    return devices if len(devices) > 1 else []


def _check_warp_spread(impl: str, mesh: Mesh) -> None:
    """ConfigError for MJX's Warp backend with a batch's episodes split over several GPUs: XLA died compiling
    those programs on 2 H200s (SIGSEGV, 2026-11-28; docs/design.md, Warp on several devices); whole batches per
    GPU run."""
    if impl == "warp" and sharding.mesh_size(mesh) > 1 and mesh.devices.flat[0].platform == "gpu":
        raise ConfigError("--impl warp splits no batch over several GPUs (XLA crashes compiling it): add --spread "
                          "batches (whole batches on each GPU) or use one GPU (--devices 1)")


def _batches_written(out: Path, total: int) -> str:
    """For Ctrl-C while batches run in any order: how many batch files the run folder holds."""
    count = sum((out / f"episodes_{k}.npz").is_file() for k in range(total))
    return f"wrote {count} of {total} batch files (episodes_<k>.npz) in {out}, no summary"


def _batch_files(count: int, total: int) -> str:
    """The batch files written, for the line Ctrl-C prints: "episodes_0.npz .. episodes_1.npz (2 of 3 batches)"."""
    files = "episodes_0.npz" if count == 1 else f"episodes_0.npz .. episodes_{count - 1}.npz"
    return f"{files} ({count} of {total} batch{'es' if total > 1 else ''})"


def _video_count(text: str) -> int:
    try:
        count = int(text)
    except ValueError:
        raise ConfigError(f"--video must be an integer >= 0 (episodes per variant), got {text!r}") from None
    require_int("--video", count, 0)
    return count


def _save_replays(out: Path, result, numbers: list[int], batch: int) -> list[tuple[str, int]]:
    """Write the batch's recorded episodes as replay files; returns their (variant, episode number)."""
    saved = []
    for replay in result.replays:
        variant, number = replay.info["variant"], numbers[replay.info["row"]]
        save_replay(replay_path(out, variant, number),
                    dataclasses.replace(replay, info={**replay.info, "episode": number, "batch": batch}))
        saved.append((variant, number))
    return saved


def _write_videos(out: Path, recorded: list[tuple[str, int]], progress: bool) -> str | None:
    """Render every recorded episode into out/videos with `python -m experiments.render episode`, each in
    its own process (MUJOCO_GL must be set before mujoco is imported), the GL backend chosen once here.
    None when every video is written, else one line: what was not rendered, why, and how to later."""
    if not recorded:
        return None
    try:
        backend = gl.choose()
    except gl.RenderError as error:
        return _not_rendered(out, recorded, str(error))
    env = dict(os.environ, MUJOCO_GL=backend, **{gl.CHECKED: backend})
    for k, (variant, number) in enumerate(tqdm(recorded, desc="videos", unit="video", disable=not progress)):
        command = [sys.executable, "-m", "experiments.render", "episode", str(out.resolve()), "--variant", variant,
                   "--episode", str(number), "--no-progress"]
        with batch_workers.no_fork_warning():
            proc = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            lines = proc.stderr.strip().splitlines() or [f"exit status {proc.returncode}"]
            return _not_rendered(out, recorded[k:], lines[-1].removeprefix("error: "))
    return None


def _not_rendered(out: Path, missing: list[tuple[str, int]], why: str) -> str:
    """The line saying the `missing` (variant, episode) videos were not rendered, why, and how to render them."""
    (variant, number), rest = missing[0], missing[1:]
    later = f"python -m experiments.render episode {out} --variant {variant} --episode {number}"
    if rest:
        later += " (then the same with " + ", ".join(f"--variant {v} --episode {i}" for v, i in rest) + ")"
    return f"videos not rendered: {why.removeprefix('cannot render: ')}. The results and replays are in {out}; render them later with: {later}"


def _print_statistics(statistics: dict) -> None:
    """The protocol table (ours beside the paper's), each variant's success rate with its interval and per-seed
    rates, and the pairwise tests at the three levels."""
    print(PAPER_METHOD_HEADER)
    print(f"{'variant':<12} {'replications':>12} {'25 / 50 / 75 % (actions)':>26} {'paper':>14} {'failed':>8} {'flipped':>8}")
    for name, v in statistics["variants"].items():
        ours = f"{v['p25']:.0f} / {v['p50']:.0f} / {v['p75']:.0f}"
        paper = " / ".join(str(q) for q in PAPER_QUARTILES[name]) if name in PAPER_QUARTILES else "-"
        print(f"{name:<12} {v['replications']:>12} {ours:>26} {paper:>14} {v['failure_percent']:>7.1f}% {v['flipped']:>8}")
    print("\n".join(level_lines(statistics)))
    reduction = statistics.get("failure_reduction")
    if reduction and reduction["percent"] is not None:
        print(f"{reduction['variant']} has {reduction['percent']:.0f} % fewer failures than {reduction['baseline']} "
              f"(paper: {reduction['paper_percent']:.0f} %)")
    reductions = statistics.get("failure_reductions")
    if reductions and any(p is not None for p in reductions["percent"].values()):
        print(f"fewer failures than {reductions['baseline']}: " + ", ".join(
            f"{name} {percent:.0f} %" for name, percent in reductions["percent"].items() if percent is not None))


def _load_batch(path: Path, seed: int, labels: list[tuple[str, str, int]]):
    """A finished batch read back from its episodes_<k>.npz: (what `_plot_batch` reads, its episode
    records); ConfigError when the file holds another batch than the one planned (`labels`)."""
    arrays, header = read_checkpoint(path)
    saved = header.get("metadata", {})
    if "records" not in saved or saved["seed"] != seed or [tuple(x) for x in zip(
            saved["variants"], saved["damages"], saved["replicates"])] != labels:
        raise ConfigError(f"--resume: {path} holds another batch than this run's; remove it to run that batch again")
    history = SimpleNamespace(**{k: arrays[k] for k in ("predicted", "observed", "path", "path_length")})
    episodes = SimpleNamespace(history=history, **{k: arrays[k] for k in ("trajectory", "taken", "reached", "broken")})
    result = SimpleNamespace(episodes=episodes, seed=seed, variants=saved["variants"], damages=saved["damages"],
                             replicates=saved["replicates"])
    return result, saved["records"]


def _save_batch(path: Path, result, records: list[dict], run_with: list[int]) -> None:
    """Batch file `path`: the episodes' arrays, their records and labels, and `run_with`, the batches run together
    with it (itself included: they share its setup, planning and acting seconds)."""
    ep = result.episodes
    damage = result.damage
    arrays = {**{k: getattr(ep, k) for k in ("trajectory", "taken", "reached", "broken")}, "damage": damage.legs,
              "damage_fraction": damage.fraction, "damage_friction": damage.friction,
              **{field.name: getattr(ep.history, field.name) for field in dataclasses.fields(ep.history)}}
    models = [list(DAMAGE_PARTS)[int(index)] for index in damage.model]
    labels = {"seed": result.seed, "variants": result.variants, "damages": result.damages, "replicates": result.replicates,
              "damage_models": models,
              "repertoire": result.repertoire, "setup_seconds": result.timings.setup, "plan_seconds": result.timings.plan,
              "act_seconds": result.timings.act, "run_with": list(run_with),
              "records": records}
    save_checkpoint(path, arrays, labels, compress=True)


def _plot_batch(plot_dir: Path, result, curves: dict, tracks: dict, maze, first_seed: int) -> None:
    """Add the batch's prediction errors to `curves`; for the run's first seed, plot its trajectories and keep them
    in `tracks`."""
    ep = result.episodes
    errors = prediction_errors(ep)
    taken = np.asarray(ep.taken)
    for variant in dict.fromkeys(result.variants):
        rows = [i for i, v in enumerate(result.variants) if v == variant]
        first = [i for i in rows if result.replicates[i] == 0]  # one episode per damage
        labels = [f"{result.damages[i]}: {'goal' if bool(ep.reached[i]) else 'failed'} in {int(taken[i])}" for i in first]
        if result.seed == first_seed:  # trajectories of the run's first repertoire seed
            plot_episodes(plot_dir / f"maze_{variant}.png", maze, ep, first, labels,
                          f"{variant}: first replicate per damage", plan_of=first[0])
            tracks[variant] = [(label, episode_track(ep, i)) for label, i in zip(labels, first)]
        masked = np.full((len(rows), errors.shape[1]), np.nan)
        for j, i in enumerate(rows):
            masked[j, : taken[i]] = errors[i, : taken[i]]
        curves[variant] = np.concatenate([curves[variant], masked]) if variant in curves else masked


if __name__ == "__main__":
    sys.exit(main())
