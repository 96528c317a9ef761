"""Which headless OpenGL backend MuJoCo renders with (`MUJOCO_GL`), chosen before `mujoco` is imported (which
loads it, and fails if it is missing); this module imports neither. `choose`: the user's MUJOCO_GL (egl, osmesa,
glfw or glx) if it starts, else EGL then OSMesa, the first that draws a frame in a short child process (a failed
GL load can break the process trying it); none: `setup()` sets MUJOCO_GL=disable and `require()` raises a one-line
`RenderError`. A process that has tried passes `HTE_JAX_GL_CHECKED=<backend>` to the render processes it starts.

    python -m hte_jax.viz.gl     # prints the backend chosen here, or the one-line reason (exit 2)
"""

from __future__ import annotations

import ctypes.util
import os
import subprocess
import sys

AUTOMATIC = ("egl", "osmesa")  # tried in this order when MUJOCO_GL is unset
ACCEPTED = ("egl", "osmesa", "glfw", "glx")  # MUJOCO_GL values kept as the user gave them
CHECKED = "HTE_JAX_GL_CHECKED"  # MUJOCO_GL's value that the parent process has just seen start
TRY_TIMEOUT_S = 120.0
NAMES = {"egl": "EGL", "osmesa": "OSMesa", "glfw": "GLFW", "glx": "GLX"}
LIBRARIES = {"egl": "EGL", "osmesa": "OSMesa", "glx": "GL"}  # what ctypes looks for (GLFW ships in its wheel)
HOW_TO_GET = ("install OSMesa (Debian/Ubuntu: apt-get install libosmesa6) or Mesa's EGL (libegl-mesa0), "
              "or use a GPU whose driver provides EGL")

# Draws one frame of an empty model with mujoco.Renderer (MUJOCO_GL from the environment).
_TRY = ("import mujoco\nrenderer = mujoco.Renderer(mujoco.MjModel.from_xml_string('<mujoco/>'), 1, 1)\n"
        "renderer.render()\nrenderer.close()\n")

_unavailable: RenderError | None = None  # why no backend starts, once setup() has found none


class RenderError(RuntimeError):
    """The OpenGL renderer cannot start (a one-line message: what was tried, why, what to install)."""


def try_backend(backend: str, env: dict | None = None, timeout: float = TRY_TIMEOUT_S) -> str | None:
    """None if mujoco starts OpenGL with `MUJOCO_GL=backend` (child process, `env` or os.environ), else why not."""
    env = dict(os.environ if env is None else env, MUJOCO_GL=backend)
    env.pop(CHECKED, None)
    try:
        proc = subprocess.run([sys.executable, "-c", _TRY], env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"no context within {timeout:g} s"
    if proc.returncode == 0:
        return None
    library = LIBRARIES.get(backend)
    if library is not None and ctypes.util.find_library(library) is None:
        return f"lib{library} not found"
    if backend in ("glfw", "glx") and not env.get("DISPLAY"):
        return "it needs a display and DISPLAY is unset"
    if proc.returncode < 0:
        return f"the child process died of signal {-proc.returncode}"
    lines = [line.strip() for line in proc.stderr.splitlines() if line.strip()]
    return _short(lines[-1]) if lines else f"exit status {proc.returncode}"


def _short(line: str, limit: int = 100) -> str:
    """An exception's last line without its type, first sentence only, at most `limit` characters."""
    kind, _, message = line.partition(": ")
    text = (message if kind.replace(".", "_").isidentifier() and message else line).split(". ")[0].rstrip(".")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def choose(env: dict | None = None, attempt=try_backend) -> str:
    """The MUJOCO_GL to render with: the one in `env` (default os.environ) if it starts, else the first of
    AUTOMATIC that starts (`attempt(backend, env)`: None or why not); RenderError if none or not a renderer."""
    env = os.environ if env is None else env
    given = env.get("MUJOCO_GL", "").strip().lower()
    if given:
        if given not in ACCEPTED:
            raise RenderError(f"MUJOCO_GL={env['MUJOCO_GL']!r} is not a renderer: use egl or osmesa, or unset it "
                              "to choose automatically (EGL, then OSMesa)")
        if env.get(CHECKED, "").strip().lower() == given:
            return given
        reason = attempt(given, env)
        if reason is not None:
            raise RenderError(f"cannot render: MUJOCO_GL={given} does not start ({reason}); {HOW_TO_GET}; "
                              "or unset MUJOCO_GL to try EGL, then OSMesa")
        return given
    reasons = []
    for backend in AUTOMATIC:
        reason = attempt(backend, env)
        if reason is None:
            return backend
        reasons.append(f"{NAMES[backend]}: {reason}")
    raise RenderError(f"cannot render: no headless OpenGL starts here ({'; '.join(reasons)}); {HOW_TO_GET}")


def setup() -> str | None:
    """Set MUJOCO_GL to this process's backend before mujoco is imported and return it (None: MUJOCO_GL=disable,
`require()` raises why); a MUJOCO_GL that is not a renderer raises; after mujoco's import nothing changes."""
    global _unavailable
    if "mujoco" in sys.modules:
        return os.environ.get("MUJOCO_GL")
    try:
        backend = choose()
    except RenderError as error:
        if os.environ.get("MUJOCO_GL", "").strip().lower() not in ("", *ACCEPTED):
            raise
        _unavailable = error
        os.environ["MUJOCO_GL"] = "disable"
        return None
    _unavailable = None
    os.environ["MUJOCO_GL"] = backend
    return backend


def require() -> None:
    """Raise the RenderError `setup()` found, if it found no backend."""
    if _unavailable is not None:
        raise _unavailable


def main() -> int:
    try:
        print(choose())
    except RenderError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
