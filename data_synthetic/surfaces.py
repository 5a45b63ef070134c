"""The synthetic scenes, selectable by name."""

from __future__ import annotations

from collections.abc import Callable

from .sphere import sphere_cap
from .surface import Surface, normals_from_height
from .tablet import clay_tablet

#: Scene builders by name; each is called as ``SCENES[name](shape, pixel_size=..., seed=...)``.
SCENES: dict[str, Callable[..., Surface]] = {"tablet": clay_tablet, "sphere": sphere_cap}

__all__ = ["SCENES", "Surface", "clay_tablet", "normals_from_height", "sphere_cap"]
