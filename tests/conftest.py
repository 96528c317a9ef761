"""Session-wide settings: XLA's cheapest CPU code generation outside the golden-output files
(`FAST_COMPILE`), a persistent XLA compilation cache shared by all tests of a session (and
by pytest-xdist workers), in-memory compiled programs released after each test module, the
controllers of an HBR's middle elites computed once per test process, the files in the order
that balances two xdist workers (`SLOWEST_FIRST`), the OpenGL backend of the tests that draw frames (`gl_env`), and the fixtures
several modules share (the default robot, the shipped HBR).

MJX programs take 15-30 s to compile on a CPU; tests that build the same program again (a
resumed training run, a re-simulation, a benchmark script re-running a training preset) then
load it from the cache instead of recompiling.
"""

import contextlib
import gc
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile

import jax
import numpy as np
import pytest

import hte_jax  # noqa: F401  (sizes XLA's CPU pool before jax starts: hte_jax/cpu_pool.py)

# The controller process makes the folder; xdist workers inherit it through the environment.
_OWNER = "HTE_JAX_TEST_XLA_CACHE" not in os.environ
_CACHE = os.environ.setdefault("HTE_JAX_TEST_XLA_CACHE", tempfile.mkdtemp(prefix="hte-jax-xla-cache-"))
# Subprocesses started by tests (benchmark scripts, CLIs) share the cache through the environment.
os.environ["JAX_COMPILATION_CACHE_DIR"] = _CACHE
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"


# Compiling MJX programs is most of the suite's time. Tests compile them with XLA's CPU code generator
# at its cheapest: the older elemental fusion emitters and LLVM without optimisation (about a third of
# the compile time, measured on 2 cores: a 300-step rollout 23 -> 5 CPU s, test_flat_aprol 204 -> 124
# CPU s; the code runs up to ~4x slower, which tests at tiny sizes barely feel). It changes the bits of
# floating-point results, so the files that compare runs with golden outputs (`DEFAULT_COMPILE`),
# and their subprocesses, compile with XLA's defaults, as `python -m tests.golden` records them.
# In-process the fast options go through the compile options of every program (`_with_compile_options`,
# so the persistent cache keys them); subprocesses read them from XLA_FLAGS, which holds them only while a
# fast file runs. This process itself starts with the user's XLA_FLAGS, so a `DEFAULT_COMPILE` file compiles
# its programs exactly as its subprocesses do (same flags, no overrides: the same persistent-cache keys,
# and a resumed command finds the programs its test compiled).
FAST_COMPILE = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 0}
FAST_FLAGS = [f"--{name}={str(value).lower()}" for name, value in FAST_COMPILE.items()]
# Golden runs (test_benchmarks_hbr re-runs the tiny HBR's programs), and files that compare two differently
# compiled paths bit for bit (a measured step against a direct rollout, the reflex's held pose, a flat
# action against its controller): under the fast mode those differ by ~1e-5 (measured 2026-11-27).
DEFAULT_COMPILE = ("test_hbr_training.py", "test_flat.py", "test_episode.py", "test_interrupts.py",
                   "test_benchmarks_hbr.py", "test_composition.py", "test_rollout.py", "test_execute.py")


def with_fast_flags(flags: str) -> str:
    """XLA_FLAGS plus the session's `FAST_FLAGS`."""
    return " ".join([*flags.split(), *FAST_FLAGS])


def _fast_compile_works() -> bool:
    """Whether this jax has the compile-options hook and its XLA knows the flags (an unknown flag
    in XLA_FLAGS aborts every process): probed once per session in a subprocess, else the suite
    compiles with XLA's defaults throughout."""
    from jax._src import compiler

    if not hasattr(compiler, "get_compile_options"):
        return False
    probe = "import jax, jax.numpy as jnp; jax.jit(lambda x: x + 1)(jnp.ones(2)).block_until_ready()"
    env = {**os.environ, "XLA_FLAGS": with_fast_flags(os.environ.get("XLA_FLAGS", "")), "JAX_PLATFORMS": "cpu"}
    return subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True).returncode == 0


# The controller process probes; xdist workers inherit the answer through the environment.
if os.environ.setdefault("HTE_JAX_TEST_FAST_COMPILE", "1" if _fast_compile_works() else "0") != "1":
    FAST_COMPILE = {}
_USER_XLA_FLAGS = os.environ.get("XLA_FLAGS", "")
_compile_with = [{}]  # what `_compile_options` adds: the running module's choice


def _with_compile_options(get_compile_options):
    def compile_options(*args, **kwargs):
        options = get_compile_options(*args, **kwargs)
        options.env_option_overrides = [*options.env_option_overrides, *_compile_with[0].items()]
        return options

    return compile_options


@contextlib.contextmanager
def _compiling(options: dict, flags: str):
    """Within it, this process compiles with the override `options` and the processes it starts read
    XLA_FLAGS `flags`; both are restored after."""
    saved = _compile_with[0], os.environ.get("XLA_FLAGS", "")
    _compile_with[0], os.environ["XLA_FLAGS"] = options, flags
    try:
        yield
    finally:
        _compile_with[0], os.environ["XLA_FLAGS"] = saved


@pytest.fixture(autouse=True, scope="module")
def _compile_mode(request):
    """Per test module: the fast code generation for every file but the `DEFAULT_COMPILE` ones (in
    this process and in the subprocesses they start), XLA's defaults for those. Compiled programs
    held in memory are dropped between modules (`_free_compiled_programs`), so none crosses from one
    mode to the other."""
    if request.path.name in DEFAULT_COMPILE or not FAST_COMPILE:
        yield
        return
    with _compiling(FAST_COMPILE, with_fast_flags(_USER_XLA_FLAGS)):
        yield


@pytest.fixture
def xla_defaults(monkeypatch):
    """The subprocesses this test starts compile with XLA's defaults even in a fast file: for the
    ones that run real sizes, where the fast mode's slower code costs more than it saves (a
    benchmark's whole-HBR lookup: 13 s at the defaults, ~290 s at LLVM -O0; loading the shipped HBR:
    4 s against ~48 s)."""
    monkeypatch.setenv("XLA_FLAGS", _USER_XLA_FLAGS)


def pytest_configure(config):
    from jax._src import compiler

    jax.devices()  # XLA reads XLA_FLAGS once, when its CPU client starts: here, with the user's flags
    if FAST_COMPILE:
        compiler.get_compile_options = _with_compile_options(compiler.get_compile_options)

    jax.config.update("jax_compilation_cache_dir", _CACHE)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def pytest_unconfigure(config):
    if _OWNER:
        shutil.rmtree(_CACHE, ignore_errors=True)


# The order in which files start (pytest-xdist's --dist loadfile hands a free worker the next file,
# `--no-loadscope-reorder` keeps this order): the slowest first, so the last files to start are
# short and both workers end together (the CI time is the slower worker's). Seconds per file in the
# suite on a 2-core machine (2026-11-27, --durations=0 summed), heaviest first; files that share
# compiled programs through the persistent cache (noted) are kept apart, so they run one after the
# other rather than side by side, and a file that re-runs another's programs comes after it. Files
# not listed (each under about a minute) follow in their own order. A file that grows past a minute
# belongs here.
SLOWEST_FIRST = (
    "test_commands.py",  # ~450: every command on 2 devices, its own subprocess
    "test_hbr_training.py",  # ~590: the tiny HBR (test_benchmarks_hbr.py and test_interrupts.py re-run it)
    "test_benchmarks.py",  # ~390 (test_replay.py runs its adaptation episode)
    "test_render.py",  # ~215
    "test_rollout.py",  # ~200 (test_solver.py runs its default robot's rollouts)
    "test_composition.py",  # ~170
    "test_seed_sets.py",  # ~165 (test_protocol.py runs its 2D-RTE episodes)
    "test_extending.py",  # ~165
    "test_flat.py",  # ~155
    "test_spare.py",  # ~135
    "test_episode.py",  # ~135
    "test_replay.py",  # ~120 (test_benchmarks.py)
    "test_readme.py",  # ~115
    "test_sharding.py",  # ~115: its own subprocess on 2 devices
    "test_flat_aprol.py",  # ~115
    "test_interrupts.py",  # ~115 (the tiny HBR's programs)
    "test_sensing.py",  # ~105
    "test_solver.py",  # ~100 (test_rollout.py)
    "test_benchmarks_hbr.py",  # ~100 (the tiny HBR's programs)
    "test_modulation.py",  # ~80
    "test_execute.py",  # ~80
    "test_protocol.py",  # ~70 (test_seed_sets.py)
    "test_backend.py",  # ~60
)


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(SLOWEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


# .ci/run sets it: there a test that needs OpenGL fails instead of skipping (CI must draw frames).
REQUIRE_GL = "HTE_JAX_REQUIRE_GL"


@pytest.fixture(scope="session")
def gl_env():
    """Environment variables for a process that draws frames: MUJOCO_GL set to the headless OpenGL
    backend that starts here, chosen once per test process as the render CLI chooses
    (`hte_jax.viz.gl.choose`: the user's MUJOCO_GL, else EGL, then OSMesa) and marked as checked.
    Every test that needs OpenGL takes it: where no backend starts it skips, the reason naming what
    to install, and with HTE_JAX_REQUIRE_GL=1 it fails."""
    from hte_jax.viz import gl

    try:
        backend = gl.choose()
        return {"MUJOCO_GL": backend, gl.CHECKED: backend}
    except gl.RenderError as error:
        reason = str(error)
    if os.environ.get(REQUIRE_GL) == "1":
        pytest.fail(f"{REQUIRE_GL}=1 and no frame can be drawn: {reason}", pytrace=False)
    pytest.skip(f"needs OpenGL: {reason}")


@pytest.fixture(scope="session")
def robot():
    """The default robot (`load_robot()`), loaded once per test process."""
    from hte_jax.sim import load_robot

    return load_robot()


@pytest.fixture(scope="session")
def shipped_hbr():
    """(HBR, top task) of the shipped repertoire, loaded once per test process."""
    from hte_jax.hbr.store import load_hbr

    hbr, task, _ = load_hbr()
    return hbr, task


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drop each module's compiled programs when it ends: a whole session's MJX executables held in
    memory at once outgrow a 24 GB CI machine (the persistent cache above still saves recompiling)."""
    yield
    jax.clear_caches()
    gc.collect()


@pytest.fixture(autouse=True, scope="session")
def _leg_controllers_once_per_process():
    """`HBR.build` (every `load_hbr`) and a spare archive's `load_spare` / `with_spare` look up each
    filled middle elite's 6 bottom elites by brute force (`middle.elite_controllers`): for the
    shipped HBR (23 641 x 6 queries against 11 088 bottom elites) several seconds of CPU, paid again
    by every test that loads it (a `maze_eval` run, a re-execution, ...). Within a test process the
    same inputs give the same controllers, so they are computed once: the result is keyed by the
    bytes of every input, and traced inputs (inside a jit) are always computed. They are computed with
    XLA's default code generation in every file: the fast mode's code takes ~45 s for the shipped HBR
    instead of ~4 s (a nearest-elite search, not a tiny test size)."""
    from hte_jax.hbr import hierarchy, middle, store, training

    compute = middle.elite_controllers
    known: dict[str, jax.Array] = {}

    def elite_controllers(bottom, genotypes, filled):
        inputs = (bottom.descriptors, bottom.filled, bottom.genotypes, genotypes, filled)
        if any(isinstance(x, jax.core.Tracer) for x in inputs):
            return compute(bottom, genotypes, filled)
        digest = hashlib.sha256()
        for x in inputs:
            x = np.asarray(x)
            digest.update(f"{x.dtype}{x.shape}".encode())
            digest.update(np.ascontiguousarray(x).tobytes())
        key = digest.hexdigest()
        if key not in known:
            with _compiling({}, _USER_XLA_FLAGS):  # as a DEFAULT_COMPILE file compiles it
                known[key] = jax.block_until_ready(compute(bottom, genotypes, filled))
        return known[key]

    with pytest.MonkeyPatch.context() as patch:
        for module in (hierarchy, store, training):  # HBR.build, load_spare, train_spare
            patch.setattr(module, "elite_controllers", elite_controllers)
        yield
