"""Where a rendered video's camera looks from (no mujoco import: commands check it before choosing OpenGL)."""

from __future__ import annotations

import dataclasses

from hte_jax.errors import require_choice, require_number

CAMERAS = ("track", "top")


@dataclasses.dataclass(frozen=True)
class Camera:
    """mode: "track" follows the base from `distance` (m), `elevation` and `azimuth` (degrees); "top" looks
    straight down on `centre` (x, y) from `distance`, image right = world +x, up = +y."""

    mode: str = "track"
    distance: float = 1.2
    elevation: float = -25.0
    azimuth: float = 135.0
    centre: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        require_choice("camera", self.mode, CAMERAS)
        require_number("camera distance", self.distance, 0.0, open_low=True)
