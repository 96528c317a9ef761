"""Rendering recorded states headless (`mujoco.Renderer`; `viz.gl.setup()` first): kinematics only, no re-simulation."""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import mujoco
import numpy as np

from hte_jax.errors import ConfigError, require_int
from hte_jax.sim.damage import Damage, damage_legs, edited_native_model
from hte_jax.sim.robot import NUM_LEGS, RobotConfig, build_spec, robot_info
from hte_jax.viz import gl
from hte_jax.viz.camera import Camera
from hte_jax.viz.gl import RenderError  # noqa: F401 (re-exported)

DAMAGED_RGBA = (0.85, 0.1, 0.1, 1.0)


def render_spec(config: RobotConfig = RobotConfig(), damage: np.ndarray | Damage | None = None,
                checks: float = 8.0) -> mujoco.MjSpec:
    """The simulation model's spec with a checkered floor (`checks` repeats per metre), the damaged legs of `damage`
    (a (6,) bool leg mask or an unbatched `Damage`) tinted."""
    spec = build_spec(config)
    spec.add_texture(name="checker", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
                     rgb1=[0.82, 0.82, 0.82], rgb2=[0.62, 0.62, 0.66], width=256, height=256)
    spec.add_material(name="checker", textures=["", "checker"], texrepeat=[checks, checks], texuniform=True)
    for geom in spec.geoms:
        if geom.name == "floor":
            geom.material = "checker"
            geom.rgba = [1.0, 1.0, 1.0, 1.0]
    legs = np.zeros(NUM_LEGS, bool) if damage is None else np.asarray(damage_legs(damage), bool)
    for leg in np.flatnonzero(legs):
        for geom in spec.geoms:
            if geom.name.startswith((f"leg_{leg}_", f"foot_{leg}")):
                geom.rgba = list(DAMAGED_RGBA)
    return spec


def render_model(config: RobotConfig = RobotConfig(), damage: np.ndarray | Damage | None = None) -> mujoco.MjModel:
    """`render_spec`'s model, with the model values a `Damage` changes (`damaged`)."""
    return damaged(render_spec(config, damage).compile(), config, damage)


def damaged(model: mujoco.MjModel, config: RobotConfig, damage: np.ndarray | Damage | None) -> mujoco.MjModel:
    """The render model `model` of `config`, or for a `Damage` a copy with the model values it changes
    (`damage.edited_native_model`: a shortened tibia drawn short)."""
    if not isinstance(damage, Damage):
        return model
    return edited_native_model(model, damage, robot_info(model, config))


def open_renderer(model: mujoco.MjModel, width: int, height: int) -> mujoco.Renderer:
    """A renderer of `width` x `height` pixels; RenderError (one line) if it cannot start."""
    require_int("width", width)
    require_int("height", height)
    gl.require()  # setup() found no backend: say why, without touching OpenGL
    try:
        with warnings.catch_warnings():  # a failing GLFW warns before it raises; the error says it all
            warnings.simplefilter("ignore")
            return mujoco.Renderer(model, height=height, width=width)
    except Exception as error:  # mujoco raises several kinds when no GL context can be made
        backend = os.environ.get("MUJOCO_GL", "(unset)")
        raise RenderError(f"the renderer could not start with MUJOCO_GL={backend} ({type(error).__name__}: "
                          f"{' '.join(str(error).split())}); choose MUJOCO_GL before mujoco is imported "
                          f"(hte_jax.viz.gl.setup()); {gl.HOW_TO_GET}") from None


def _camera(camera: Camera, base: np.ndarray) -> mujoco.MjvCamera:
    view = mujoco.MjvCamera()
    view.type = mujoco.mjtCamera.mjCAMERA_FREE
    if camera.mode == "track":
        view.lookat[:] = (base[0], base[1], 0.1)
        view.distance, view.elevation, view.azimuth = camera.distance, camera.elevation, camera.azimuth
    else:
        view.lookat[:] = (camera.centre[0], camera.centre[1], 0.0)
        view.distance, view.elevation, view.azimuth = camera.distance, -90.0, 90.0
    return view


def posed(model: mujoco.MjModel, qpos: np.ndarray) -> Iterator[mujoco.MjData]:
    """For each state of `qpos` (T, nq), the model's data (one MjData, updated) with it set and its kinematics."""
    qpos = np.asarray(qpos, np.float64)
    if qpos.ndim != 2 or qpos.shape[1] != model.nq:
        raise ConfigError(f"qpos must have shape (T, {model.nq}), got {qpos.shape}")
    data = mujoco.MjData(model)
    for state in qpos:
        data.qpos[:] = state
        mujoco.mj_kinematics(model, data)
        yield data


def render_frames(model: mujoco.MjModel, qpos: np.ndarray, renderer: mujoco.Renderer, camera: Camera = Camera(),
                  progress=None, decorate: Callable[[int, mujoco.MjvScene], None] | None = None) -> np.ndarray:
    """Frames (T, H, W, 3) uint8 of the recorded states `qpos` (T, nq); decorate(t, scene) adds geoms to frame t."""
    frames = np.empty((len(qpos), renderer.height, renderer.width, 3), np.uint8)
    for t, data in enumerate(posed(model, qpos)):
        mujoco.mj_camlight(model, data)
        renderer.update_scene(data, camera=_camera(camera, data.qpos[:3]))
        if decorate is not None:
            decorate(t, renderer.scene)
        frames[t] = renderer.render()
        if progress is not None:
            progress.update(1)
    return frames


def label(frames: np.ndarray, text: str | Sequence[str], background: tuple[int, int, int] | None = None) -> np.ndarray:
    """Frames (T, H, W, 3) with `text` (one, or one per frame) top-left, on a `background` box if given."""
    from PIL import Image, ImageDraw
    texts = [text] * len(frames) if isinstance(text, str) else list(text)
    if len(texts) != len(frames):
        raise ConfigError(f"{len(texts)} labels for {len(frames)} frames")
    out = np.empty_like(frames)
    for t, (frame, words) in enumerate(zip(frames, texts)):
        image = Image.fromarray(frame)
        draw = ImageDraw.Draw(image)
        if background is not None:
            left, top, right, bottom = draw.multiline_textbbox((4, 3), words)
            draw.rectangle((0, 0, right + 3, bottom + 3), fill=background)
        draw.multiline_text((4, 3), words, fill=(10, 10, 10))
        out[t] = np.asarray(image)
    return out


def tile(videos: list[np.ndarray], columns: int) -> np.ndarray:
    """Lay equally long videos (T, H, W, 3) out on a grid of `columns` (black where none)."""
    require_int("columns", columns)
    count, (frames, height, width, _) = len(videos), videos[0].shape
    rows = -(-count // columns)
    grid = np.zeros((frames, rows * height, columns * width, 3), np.uint8)
    for k, video in enumerate(videos):
        r, c = divmod(k, columns)
        grid[:, r * height:(r + 1) * height, c * width:(c + 1) * width] = video
    return grid


def write_video(path: str | Path, frames: np.ndarray, fps: float) -> Path:
    """Write frames (T, H, W, 3) uint8 as MP4 or GIF, by suffix (no usable ffmpeg: a .gif); returns the path."""
    path = Path(path)
    if path.suffix not in (".mp4", ".gif"):
        raise ConfigError(f"video file must end in .mp4 or .gif, got {path.name!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".mp4":
        try:
            import imageio_ffmpeg
            _write_mp4(path, frames, fps, imageio_ffmpeg)
            return path
        except (ImportError, OSError, RuntimeError):
            path = path.with_suffix(".gif")
    from PIL import Image
    images = [Image.fromarray(frame) for frame in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0, optimize=True)
    return path


def _write_mp4(path: Path, frames: np.ndarray, fps: float, imageio_ffmpeg) -> None:
    height, width = frames.shape[1:3]
    pad = np.zeros((frames.shape[0], height + height % 2, width + width % 2, 3), np.uint8)  # H.264: even sizes
    pad[:, :height, :width] = frames
    with warnings.catch_warnings():  # ffmpeg is a subprocess: JAX's fork warning does not apply to exec
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        writer = imageio_ffmpeg.write_frames(str(path), (pad.shape[2], pad.shape[1]), fps=fps, quality=7,
                                             macro_block_size=1, ffmpeg_log_level="error")
        writer.send(None)
        for frame in pad:
            writer.send(np.ascontiguousarray(frame))
        writer.close()
