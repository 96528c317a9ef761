"""Does a killed `train_hbr` resume to the same HBR, wherever it is killed?

Runs `python -m experiments.train_hbr --preset tiny --out DIR` once to the end (the reference),
then, for every scenario, runs it again in a folder of its own, kills it with SIGKILL at a kill
point, resumes it with `--resume` (killing the resume too where a scenario names several points)
and finally resumes it to the end. The final `hbr.npz` is compared with the reference's: every
array bit for bit, the header (configuration, statistics, per-layer counts and QD scores; wall
times and device names aside), `summary.json`'s repertoire statistics and every layer's
metrics.csv (wall times aside).

Kill points are reached by watching the run, not by wall-clock luck: the run folder is polled
every few milliseconds (which layer checkpoints hold which generation, which temporary files
exist) and, where a point names one, the main thread's Python stack is read (the command runs
through `runpy` with `faulthandler` printing every thread's stack on SIGUSR1). Once a point is
reached the process is stopped (SIGSTOP), the folder and the stack are recorded, and it is killed
(SIGKILL). Points (layer L in bottom, middle, top; b a block of that layer):

    L:initial   in L's initial random batch (compilation or evaluation), before its first checkpoint
    L:block<b>  once the checkpoint of block b-1 is on disk (L's first checkpoint not yet, for b = 0)
    L:write<b>  while block b's checkpoint is written: its temporary file complete, not yet renamed
                (HTE_JAX_CHECKPOINT_PAUSE makes `qd.io.save_checkpoint` sleep there)
    steps       in the step model's measurement, after the three layers
    hbr-write   while hbr.npz is written: its temporary file complete, not yet renamed
    plots       while the plots are drawn, after hbr.npz and summary.json are written

A scenario is one point, or several joined by "+" (the first kills the run, the next kills its
resume, and so on). "landed in" is where the stack says the main thread was when it was stopped.

    python benchmarks/resume_kill.py                                # the default 17 scenarios
    python benchmarks/resume_kill.py --scenarios bottom:block1,middle:write0
    python benchmarks/resume_kill.py --scenarios bottom:block1+middle:write0   # one run, killed twice
    python benchmarks/resume_kill.py --reference runs/hbr-tiny     # an uninterrupted run made before
    python benchmarks/resume_kill.py --list                         # the points of the preset

Every process shares one persistent XLA compilation cache (the reference fills it; --no-cache:
none), which changes no result. Prints a table (scenario, where each kill landed, resumes,
temporary files left, identical) and writes JSON to benchmarks/results/ (device, date, commands).
Exit status 1 if any scenario is not identical or a kill point was not reached.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import environment, result_path  # noqa: E402
from hte_jax.hbr.training import LAYERS, preset  # noqa: E402
from hte_jax.qd.io import PAUSE_BEFORE_RENAME  # noqa: E402

# `python -m experiments.train_hbr ARGS`, with every thread's Python stack appended to DUMP on SIGUSR1.
WRAPPER = ("import faulthandler, runpy, signal, sys; "
           "faulthandler.register(signal.SIGUSR1, file=open(sys.argv.pop(1), 'a'), all_threads=True); "
           "runpy.run_module('experiments.train_hbr', run_name='__main__', alter_sys=True)")
FRAME = re.compile(r'^\s+File "(.*)", line (\d+) in (.*)$')
POLL_S = 0.005  # run folder
STACK_POLL_S = 0.1  # stack, where a point needs one


def _parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="tiny", help="train_hbr preset (default tiny)")
    p.add_argument("--scenarios", default=None,
                   help="comma-separated scenarios, each a point or points joined by '+' (default: see --list)")
    p.add_argument("--reference", type=Path, default=None,
                   help="a finished uninterrupted run of the same preset (default: run one first)")
    p.add_argument("--work-dir", type=Path, default=None,
                   help="folder for the runs and their logs (default: a temporary folder, removed after)")
    p.add_argument("--pause", type=float, default=2.0,
                   help=f"seconds each checkpoint write waits before its rename in runs killed mid-write "
                        f"({PAUSE_BEFORE_RENAME}; default 2)")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds allowed per process (default 3600)")
    p.add_argument("--no-cache", action="store_true", help="no persistent compilation cache")
    p.add_argument("--list", action="store_true", help="print the kill points and default scenarios, and exit")
    p.add_argument("--out", type=Path, default=None, help="JSON path (default: results/resume_kill_<preset>_<device>_<date>.json)")
    return p.parse_args(argv)


# ---------------------------------------------------------------------------------------------
# The run folder


def _generation(path: Path, cache: dict) -> int | None:
    """The generation a layer checkpoint holds (None: no checkpoint), read again only when it changes."""
    try:
        stat = path.stat()
    except FileNotFoundError:
        return None
    stamp = (stat.st_mtime_ns, stat.st_ino, stat.st_size)
    if cache.get(path, (None,))[0] != stamp:
        with np.load(path) as data:  # renamed into place whole: never partly written
            cache[path] = (stamp, int(data["generation"]))
    return cache[path][1]


def temporaries(out: Path) -> list[str]:
    """Temporary files of interrupted writes in a run folder (relative paths)."""
    return sorted(str(p.relative_to(out)) for p in out.rglob(".*.tmp-*"))


def snapshot(out: Path, cache: dict) -> dict:
    """What the run folder shows: each layer's checkpoint generation, metrics and temporary files;
    whether hbr.npz, its temporary file and summary.json exist."""
    layers = {}
    for layer in LAYERS:
        folder = out / layer
        layers[layer] = {"generation": _generation(folder / "checkpoint.npz", cache),
                         "metrics": (folder / "metrics.csv").exists(),
                         "temporary": any(folder.glob(".checkpoint.npz.tmp-*"))}
    return {"config": (out / "config.json").exists(), "layers": layers, "hbr": (out / "hbr.npz").exists(),
            "hbr_temporary": any(out.glob(".hbr.npz.tmp-*")), "summary": (out / "summary.json").exists()}


# ---------------------------------------------------------------------------------------------
# Kill points


class Point:
    """A kill point: `ready(snapshot)` says the run folder has reached it; `frame` (file suffix,
    function, text of the line or None), if given, must also be on the main thread's stack."""

    def __init__(self, name, ready, frame=None, pause=False):
        self.name, self.ready, self.frame, self.pause = name, ready, frame, pause


def points(config) -> dict[str, Point]:
    """Every kill point of a configuration, by name."""
    finals = {layer: getattr(config, layer).generations for layer in LAYERS}

    def after_block(layer, block):  # the generation of a layer's checkpoint after `block` (None: before block 0)
        schedule = getattr(config, layer)
        return None if block < 0 else min(schedule.block_size * (block + 1), schedule.generations)

    def done_before(s, layer):
        earlier = LAYERS[: LAYERS.index(layer)]
        return s["config"] and all(s["layers"][e]["generation"] == finals[e] for e in earlier)

    out = {}
    for layer in LAYERS:
        schedule = getattr(config, layer)
        blocks = -(-schedule.generations // schedule.block_size)
        out[f"{layer}:initial"] = Point(
            f"{layer}:initial",
            lambda s, L=layer: done_before(s, L) and s["layers"][L]["generation"] is None,
            ("qd/loop.py", "start_or_resume", "algo.init("))
        for block in range(blocks):
            if block == 0:
                ready = (lambda s, L=layer: done_before(s, L) and s["layers"][L]["metrics"]
                         and s["layers"][L]["generation"] is None)
            else:
                ready = lambda s, L=layer, g=after_block(layer, block - 1): s["layers"][L]["generation"] == g  # noqa: E731
            out[f"{layer}:block{block}"] = Point(f"{layer}:block{block}", ready)
            out[f"{layer}:write{block}"] = Point(
                f"{layer}:write{block}",
                lambda s, L=layer, g=after_block(layer, block - 1): (done_before(s, L) and s["layers"][L]["temporary"]
                                                                    and s["layers"][L]["generation"] == g),
                ("qd/io.py", "save_checkpoint", "time.sleep("), pause=True)
    out["steps"] = Point("steps", lambda s: s["layers"]["top"]["generation"] == finals["top"],
                         ("hbr/composition.py", "measure_steps", None))
    out["hbr-write"] = Point("hbr-write", lambda s: s["hbr_temporary"], ("qd/io.py", "save_checkpoint", "time.sleep("),
                             pause=True)
    out["plots"] = Point("plots", lambda s: s["summary"], ("hbr/plots.py", "plot_hbr", None))
    return out


def default_scenarios(config) -> list[str]:
    """Inside every layer (its initial batch, its first two blocks, its first checkpoint write), the
    middle layer's last write, the step model, hbr.npz's write, the plots, and a killed resume."""
    names = []
    for layer in LAYERS:
        blocks = -(-getattr(config, layer).generations // getattr(config, layer).block_size)
        names += [f"{layer}:initial", f"{layer}:block0", f"{layer}:write0"] + ([f"{layer}:block1"] if blocks > 1 else [])
    last = -(-config.middle.generations // config.middle.block_size) - 1
    if last > 0:
        names.append(f"middle:write{last}")
    return names + ["steps", "hbr-write", "plots", f"middle:block{last}+top:write0"]


# ---------------------------------------------------------------------------------------------
# The stack


def read_stack(dump: Path, pid: int, timeout: float = 5.0) -> list[tuple[str, int, str]] | None:
    """The main thread's frames, innermost first, printed by the process on SIGUSR1 (None: no answer)."""
    before = dump.stat().st_size if dump.exists() else 0
    os.kill(pid, signal.SIGUSR1)
    deadline, size, steady = time.monotonic() + timeout, before, 0
    while time.monotonic() < deadline and steady < 3:  # written once it stops growing
        time.sleep(0.005)
        now = dump.stat().st_size if dump.exists() else 0
        steady = steady + 1 if now == size and now > before else 0
        size = now
    if size == before:
        return None
    with open(dump) as handle:
        handle.seek(before)
        text = handle.read()
    threads = re.split(r"^(?:Current thread|Thread) 0x[0-9a-f]+ \(most recent call first\):\n", text, flags=re.M)
    for block in threads:
        frames = [(m[1], int(m[2]), m[3]) for m in map(FRAME.match, block.splitlines()) if m]
        if frames and frames[-1][2] == "<module>" and frames[-1][0] == "<string>":  # the wrapper's thread
            return frames
    return None


def _line(path: str, number: int) -> str:
    try:
        return Path(path).read_text().splitlines()[number - 1].strip()
    except (OSError, IndexError):
        return ""


def on_stack(frames, frame) -> bool:
    suffix, function, text = frame
    return any(f.endswith(suffix) and fn == function and (text is None or text in _line(f, n)) for f, n, fn in frames)


def landed(frames, state: dict, config) -> str:
    """Where the main thread was, in words: the phase (from its stack) and the layer (from the folder)."""
    layer = next((L for L in LAYERS if state["layers"][L]["generation"] != getattr(config, L).generations), None)
    generation = state["layers"][layer]["generation"] if layer else None
    block = 0 if generation is None else -(-generation // getattr(config, layer).block_size)
    if frames is None:
        return f"{layer or 'after the layers'}: (no stack)"
    names = [fn for _, _, fn in frames]
    for path, number, function in frames:  # innermost first
        text = _line(path, number)
        if function == "save_checkpoint":
            what = "hbr.npz" if "save_hbr" in names else f"{layer}: block {block}'s checkpoint"
            return f"{what}: temp file written, not renamed" if "time.sleep(" in text else f"{what}: being written"
        if function == "measure_steps":
            return "step model (measure_steps)"
        if function == "plot_hbr":
            return "plots (plot_hbr)"
        if function == "start_or_resume" and path.endswith("qd/loop.py"):
            return f"{layer}: initial batch" if "algo.init(" in text else f"{layer}: loading its checkpoint"
        if function == "run" and path.endswith("qd/loop.py"):
            if "run_block(" in text:
                return f"{layer}: block {block} (run_block)"
            return f"{layer}: after block {block - 1} ({text.split('(')[0].split('=')[-1].strip()})"
        if function == "train_hbr":
            return f"{layer or 'after the layers'}: train_hbr ({text})"
    return f"{layer or 'after the layers'}: {frames[0][2]}"


# ---------------------------------------------------------------------------------------------
# Runs


def command(out: Path, preset_name: str, resume: bool) -> list[str]:
    return ["--preset", preset_name, "--out", str(out), *(["--resume"] if resume else [])]


def start(out: Path, preset_name: str, resume: bool, env: dict, log: Path, dump: Path):
    args = [sys.executable, "-c", WRAPPER, str(dump), *command(out, preset_name, resume)]
    with open(log, "ab") as handle:
        return subprocess.Popen(args, cwd=ROOT, env=env, stdout=handle, stderr=subprocess.STDOUT)


def finish(proc, timeout: float, log: Path) -> None:
    try:
        code = proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise SystemExit(f"train_hbr ran longer than {timeout:.0f} s; log: {log}") from None
    if code != 0:
        tail = log.read_text(errors="replace").replace("\r", "\n").strip().splitlines()[-5:]
        raise SystemExit(f"train_hbr exited {code}; log {log}:\n" + "\n".join(tail))


def kill_at(proc, point: Point, out: Path, dump: Path, config, timeout: float) -> dict:
    """Watch the run until it reaches `point`, then stop it, record where it is, and SIGKILL it."""
    cache, began, next_stack = {}, time.monotonic(), 0.0
    while not dump.exists() and proc.poll() is None:  # SIGUSR1 ends a process that has not set its handler yet
        time.sleep(POLL_S)
    while True:
        if proc.poll() is not None:
            return {"point": point.name, "killed": False, "landed": f"not reached: the run exited {proc.returncode}"}
        if time.monotonic() - began > timeout:
            proc.kill()
            proc.wait()
            return {"point": point.name, "killed": False, "landed": "not reached within the timeout"}
        state = snapshot(out, cache)
        if point.ready(state) and (point.frame is None or time.monotonic() >= next_stack):
            if point.frame is None or on_stack(read_stack(dump, proc.pid) or [], point.frame):
                break
            next_stack = time.monotonic() + STACK_POLL_S
        time.sleep(POLL_S)
    os.kill(proc.pid, signal.SIGSTOP)  # frozen: the folder and stack below are where it is killed
    state = snapshot(out, cache)
    os.kill(proc.pid, signal.SIGCONT)  # SIGUSR1 is handled first: the stack is printed, then it is killed
    frames = read_stack(dump, proc.pid)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    return {"point": point.name, "killed": True, "landed": landed(frames, state, config), "folder": state,
            "stack": [f"{Path(f).name}:{n} {fn}" for f, n, fn in (frames or [])[:8]],
            "after_s": round(time.monotonic() - began, 2), "temporary_files": temporaries(out)}


# ---------------------------------------------------------------------------------------------
# Comparison


def _strip(value, drop=("wall_time_s", "devices")):
    if isinstance(value, dict):
        return {k: _strip(v, drop) for k, v in value.items() if k not in drop}
    if isinstance(value, list):
        return [_strip(v, drop) for v in value]
    return value


def _metrics(path: Path) -> list[list[str]]:
    rows = [line.split(",") for line in path.read_text().splitlines()]
    column = rows[0].index("wall_time_s")
    return [row[:column] + row[column + 1:] for row in rows]


def compare(run: Path, reference: Path) -> dict:
    """Differences between a resumed run and the reference: arrays of hbr.npz (bit for bit, with
    dtype and shape), its header, summary.json's statistics, the layers' metrics."""
    with np.load(run / "hbr.npz") as a, np.load(reference / "hbr.npz") as b:
        names = sorted((set(a.files) | set(b.files)) - {"__metadata__"})
        arrays = [n for n in names if n not in a.files or n not in b.files or a[n].dtype != b[n].dtype
                  or a[n].shape != b[n].shape or a[n].tobytes() != b[n].tobytes()]
        headers = [_strip(json.loads(str(x["__metadata__"]))) for x in (a, b)]
    summaries = [json.loads((r / "summary.json").read_text()) for r in (run, reference)]
    metrics = [L for L in LAYERS if _metrics(run / L / "metrics.csv") != _metrics(reference / L / "metrics.csv")]
    result = {"arrays_compared": len(names), "arrays_differing": arrays,
              "header_identical": headers[0] == headers[1],
              "statistics_identical": summaries[0]["statistics"] == summaries[1]["statistics"],
              "metrics_differing": metrics}
    result["identical"] = (not result["arrays_differing"] and result["header_identical"]
                           and result["statistics_identical"] and not metrics)
    return result


# ---------------------------------------------------------------------------------------------


def run_scenario(name: str, table: dict, config, args, env: dict, work: Path, reference: Path) -> dict:
    out = work / name.replace(":", "_").replace("+", "__")
    log = out.with_suffix(".log")
    began = time.perf_counter()
    kills, resumes = [], 0
    for i, point in enumerate(table[p] for p in name.split("+")):
        penv = dict(env, **({PAUSE_BEFORE_RENAME: str(args.pause)} if point.pause else {}))
        dump = out.with_suffix(f".stacks{i}")  # one per process: it exists once the handler is set
        proc = start(out, args.preset, i > 0, penv, log, dump)
        resumes += i > 0
        try:
            kills.append(kill_at(proc, point, out, dump, config, args.timeout))
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        if not kills[-1]["killed"]:
            return {"scenario": name, "kills": kills, "resumes": resumes, "identical": False,
                    "error": f"kill point {point.name} not reached", "wall_s": time.perf_counter() - began}
    proc = start(out, args.preset, True, env, log, out.with_suffix(".stacks"))
    finish(proc, args.timeout, log)
    resumes += 1
    same = compare(out, reference)
    config_same = json.loads((out / "config.json").read_text()) == json.loads((reference / "config.json").read_text())
    return {"scenario": name, "kills": kills, "resumes": resumes, "temporary_files_at_end": temporaries(out),
            "config_matches_reference": config_same, **same, "identical": same["identical"] and config_same,
            "wall_s": round(time.perf_counter() - began, 1)}


def main(argv=None) -> int:
    args = _parse(argv)
    config = preset(args.preset)
    table = points(config)
    scenarios = default_scenarios(config) if args.scenarios is None else [s.strip() for s in args.scenarios.split(",") if s.strip()]
    if args.list:
        print("points:   " + " ".join(table))
        print("scenarios (default): " + ",".join(default_scenarios(config)))
        return 0
    unknown = sorted({p for s in scenarios for p in s.split("+")} - set(table))
    if unknown or not scenarios:
        raise SystemExit(f"--scenarios: unknown kill points {unknown}; --list shows them")
    if args.reference is not None and not (args.reference / "hbr.npz").exists():
        raise SystemExit(f"--reference {args.reference}: no hbr.npz there (not a finished train_hbr run)")
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="resume-kill-"))
    work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.pop(PAUSE_BEFORE_RENAME, None)
    if not args.no_cache and "JAX_COMPILATION_CACHE_DIR" not in env:
        env.update(JAX_COMPILATION_CACHE_DIR=str(work / "xla-cache"), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                   JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
    machine = environment()
    rows, reference_s = [], None
    try:
        reference = args.reference
        if reference is None:
            reference = work / "reference"
            began = time.perf_counter()
            print(f"reference: an uninterrupted run in {reference}", flush=True)
            finish(start(reference, args.preset, False, env, reference.with_suffix(".log"),
                         reference.with_suffix(".stacks")), args.timeout, reference.with_suffix(".log"))
            reference_s = round(time.perf_counter() - began, 1)
        for name in scenarios:
            print(f"scenario {name} ...", flush=True)
            rows.append(run_scenario(name, table, config, args, env, work, reference))
            row = rows[-1]
            print(f"  {' | '.join(k['landed'] for k in row['kills'])}; identical: {row['identical']} "
                  f"({row['wall_s']} s)", flush=True)
    finally:
        if args.work_dir is None:
            shutil.rmtree(work, ignore_errors=True)
    width = max(len(r["scenario"]) for r in rows)
    landed_width = max(len(" | ".join(k["landed"] for k in r["kills"])) for r in rows)
    print(f"\n{'kill point':<{width}}  {'landed in':<{landed_width}}  resumes  temp files left  identical")
    for r in rows:
        left = f"{len(r['kills'][-1].get('temporary_files', []))} -> {len(r.get('temporary_files_at_end', []))}"
        print(f"{r['scenario']:<{width}}  {' | '.join(k['landed'] for k in r['kills']):<{landed_width}}  "
              f"{r['resumes']:>7}  {left:>15}  {'yes' if r['identical'] else 'NO'}")
    identical = sum(r["identical"] for r in rows)
    print(f"{identical} of {len(rows)} scenarios identical to the uninterrupted run "
          f"(temp files left: after the last kill -> after the final resume)")
    path = args.out or result_path(f"resume_kill_{args.preset}", machine)
    result = {
        "environment": machine,
        "command": "python benchmarks/resume_kill.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "train_hbr": "python -m experiments.train_hbr " + " ".join(command(Path("DIR"), args.preset, False))
                     + " (then the same with --resume), through runpy with faulthandler on SIGUSR1",
        "preset": args.preset, "config": config.to_dict(), "pause_s": args.pause,
        "compilation_cache": not args.no_cache, "reference": str(args.reference) if args.reference else None,
        "reference_wall_s": reference_s, "scenarios": rows, "identical": identical, "total": len(rows),
    }
    Path(path).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}")
    return 0 if identical == len(rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
