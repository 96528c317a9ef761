"""The suite's machinery (tests/README.md says where a new test goes and which markers it takes):

- XLA's CPU code generation per test (tests/xla_codegen.py): the cheapest, or XLA's defaults for a test
  marked `exact_numerics`;
- one persistent XLA compilation cache for the session, its pytest-xdist workers and the processes the
  tests start (MJX programs take 15-30 s to compile on a CPU: a resumed run, a re-simulation or a
  benchmark re-running a preset loads them), and compiled programs dropped from memory between xdist groups;
- pytest-xdist groups (`--dist loadgroup`): a test file is one group unless it names one, and the groups
  that hold `slow` tests start first;
- a test past its time limit (pytest-timeout) in a pytest-xdist worker: every thread's stack on stderr;
- the fixtures several modules share (the default robot, the shipped HBR, the OpenGL environment).
"""

import faulthandler
import gc
import os
import shutil
import sys
import tempfile
import threading

import jax
import pytest

import hte_jax  # noqa: F401  (sizes XLA's CPU pool before jax starts: hte_jax/cpu_pool.py)
from tests import xla_codegen

# The controller process makes the folder; xdist workers inherit it through the environment.
_OWNER = "HTE_JAX_TEST_XLA_CACHE" not in os.environ
_CACHE = os.environ.setdefault("HTE_JAX_TEST_XLA_CACHE", tempfile.mkdtemp(prefix="hte-jax-xla-cache-"))
# Subprocesses started by tests (benchmark scripts, CLIs) share the cache through the environment.
os.environ["JAX_COMPILATION_CACHE_DIR"] = _CACHE
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"


def pytest_configure(config):
    jax.devices()  # XLA reads XLA_FLAGS once, when its CPU client starts: here, with the user's flags
    xla_codegen.install()
    jax.config.update("jax_compilation_cache_dir", _CACHE)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def pytest_unconfigure(config):
    if _OWNER:
        shutil.rmtree(_CACHE, ignore_errors=True)


_held_group: str | None = None  # the xdist group whose compiled programs this process holds


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    """Each test, its fixtures included, compiles with the fast options unless marked `exact_numerics`
    (tests/xla_codegen.py). This process keeps the user's XLA_FLAGS and gives the fast options to each
    program; the processes a fast test starts read them from XLA_FLAGS. So an `exact_numerics` test's
    programs and those of the commands it starts have the same persistent-cache keys (same flags, no
    options): a resumed command finds the programs its test compiled.

    A process holds the compiled programs (and traced functions) of one xdist group at a time: they are
    dropped when a test of another group starts. A whole session's MJX executables held in memory at once
    outgrow a 24 GB CI machine, while the files of one group run the same programs in this process (the
    tiny HBR of hbr_tiny: 171 s cold, 45 s from the persistent cache, which still traces every function,
    22 s from memory)."""
    global _held_group
    group = _group(item)
    if group != _held_group:
        jax.clear_caches()
        gc.collect()
        _held_group = group
    xla_codegen.use(fast=item.get_closest_marker("exact_numerics") is None)


@pytest.fixture
def xla_defaults(monkeypatch):
    """The processes this test starts compile at XLA's defaults even in a fast test: for the ones that run
    real sizes, where the fast mode's slower code costs more than it saves (a benchmark's whole-HBR
    lookup: 13 s at the defaults, ~290 s at LLVM -O0; loading the shipped HBR: 4 s against ~48 s)."""
    monkeypatch.setenv("XLA_FLAGS", xla_codegen.USER_FLAGS)


def _group(item) -> str:
    mark = item.get_closest_marker("xdist_group")
    return str(mark.args[0] if mark.args else mark.kwargs.get("name", "default"))


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(session, config, items):
    """Each test file is an xdist group of its own unless its tests name one (`--dist loadgroup` runs a group
    on one worker, in order: a module's fixtures are made once); the groups that hold `slow` tests first, so
    that both workers end together (list scheduling: the long units first, the short ones fill in)."""
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(item.path.stem))
    group = {item: _group(item) for item in items}
    slow = {group[item] for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: group[item] not in slow)


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_timeout_set_timer(item, settings):
    """pytest-timeout's thread method, its report kept: in a pytest-xdist worker it writes a timed-out test's
    stacks to stdout, which the worker drops. Here they go to stderr (the run's log), then the worker ends:
    xdist reports the test as failed ("worker crashed while running it") and, with --max-worker-restart=0,
    ends the run rather than run the test again."""
    if not hasattr(item.config, "workerinput") or settings.timeout <= 0:
        return None  # pytest-timeout's own timer

    def expire():
        capture = item.config.pluginmanager.getplugin("capturemanager")
        if capture is not None:
            capture.suspend_global_capture(item)
        sys.stderr.write(f"\n+++ {item.nodeid} ran past its {settings.timeout:g} s limit; the stacks:\n")
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        sys.stderr.flush()
        os._exit(1)

    timer = threading.Timer(settings.timeout, expire)
    timer.daemon = True
    timer.start()
    item.cancel_timeout = timer.cancel  # what pytest-timeout's cancel hook calls
    return True


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


@pytest.fixture(scope="session", autouse=True)
def shipped_hbr():
    """(HBR, top task) of the shipped repertoire, loaded once per test process before its first test, at
    XLA's default code generation: the middle elites' bottom-elite lookup takes ~7 CPU s there and ~26 s
    in the fast mode, and `hbr.middle.elite_controllers` keeps its result, so that every later load of the
    shipped HBR in the process (a test's own `load_hbr()`, a command run in-process) skips it."""
    from hte_jax.hbr.store import load_hbr

    with xla_codegen.at_defaults():
        hbr, task, _ = load_hbr()
    return hbr, task


