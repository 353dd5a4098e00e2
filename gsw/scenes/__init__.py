"""Procedural scenes for tests, benchmarks, demos and as training ground truth."""

from __future__ import annotations

from gsw.scenes.synthetic import (
    DEFAULT_SCENE_CENTER,
    SyntheticScene,
    default_cameras,
    default_scene,
    frustum_scene,
    frustum_sigma_px,
    heavy_scene,
    random_gaussians,
)

__all__ = [
    "DEFAULT_SCENE_CENTER", "SyntheticScene", "default_cameras", "default_scene", "frustum_scene",
    "frustum_sigma_px", "heavy_scene", "random_gaussians",
]
