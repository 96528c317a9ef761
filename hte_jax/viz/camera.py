"""Where a rendered video's camera looks from (no mujoco import: commands check it before choosing OpenGL)."""

from __future__ import annotations

import dataclasses

from hte_jax.errors import require_choice, require_number

CAMERAS = ("track", "top")


@dataclasses.dataclass(frozen=True)
class Camera:
    """Where the camera looks from."""

    mode: str = "track"  # "track" follows the base; "top" looks down on `centre` (image right = world +x, up = +y)
    distance: float = 1.2  # m
    elevation: float = -25.0  # degrees (track)
    azimuth: float = 135.0  # degrees (track)
    centre: tuple[float, float] = (0.0, 0.0)  # (x, y) (top)

    def __post_init__(self):
        require_choice("camera", self.mode, CAMERAS)
        require_number("camera distance", self.distance, 0.0, open_low=True)
