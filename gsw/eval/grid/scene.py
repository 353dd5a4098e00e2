"""The model a grid watermarks and its views: the built-in scene or an INRIA model folder (+ its dataset)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.gaussians import Gaussians

__all__ = ["GridScene", "default_grid_scene", "load_grid_scene"]


@dataclass
class GridScene:
    """A model to watermark and its views.

    Attributes:
        gaussians: the original model.
        cameras: embedding (training) views.
        eval_cameras: held-out evaluation views.
        images: ``[V, 3, H, W]`` training images for FGD phase 1, or None.
        background: RGB render background.
        key: JSON identity of the scene (stored in ``grid.json``).
    """

    gaussians: Gaussians
    cameras: list[Camera]
    eval_cameras: list[Camera]
    images: Tensor | None
    background: tuple[float, float, float]
    key: dict[str, Any]

    def __post_init__(self) -> None:
        if not self.cameras or not self.eval_cameras:
            raise ValueError("a grid scene needs training and evaluation views")

    def to(self, device: torch.device | str) -> "GridScene":
        """The same scene with its Gaussians and images on `device` (cameras stay plain data)."""
        return dataclasses.replace(self, gaussians=self.gaussians.to(device),
                                   images=None if self.images is None else self.images.to(device))


def _first(items: Sequence, n: int | None, what: str) -> list:
    if n is not None and not 0 < n <= len(items):  # n = None: all
        raise ValueError(f"{what} must be in 1..{len(items)}, got {n}")
    return list(items[:n])


def _spread(n_items: int, n: int | None, what: str) -> list[int]:
    """``n`` evenly spaced indices of ``n_items`` (all when ``n`` is None)."""
    if n is None:
        return list(range(n_items))
    if not 0 < n <= n_items:
        raise ValueError(f"{what} must be in 1..{n_items}, got {n}")
    return [i * n_items // n for i in range(n)]


def default_grid_scene(size: int = 64, views: int = 24, *, eval_views: int | None = None,
                       detail: float = 1.0) -> GridScene:
    """The built-in scene (:func:`gsw.scenes.default_scene`, white background).

    Args:
        size: render width and height, pixels.
        views: embedding views (an orbit).
        eval_views: evaluation views: the first of the orbit shifted by half a step (default: ``views``).
        detail: Gaussian density factor.

    Returns:
        A :class:`GridScene` without images.
    """
    from gsw.scenes import default_cameras, default_scene

    scene = default_scene(width=size, height=size, n_cameras=views, detail=detail)
    held_out = default_cameras(views, size, size, azimuth_offset_deg=180.0 / views)
    held_out = _first(held_out, eval_views, "eval_views")
    bg = tuple(float(v) for v in scene.background)
    key = dict(kind="default", size=size, views=views, eval_views=len(held_out), detail=detail)
    return GridScene(scene.gaussians, scene.cameras, held_out, None, bg, key)


def load_grid_scene(model: str | Path, data: str | Path | None = None, *, downscale: float = 1.0,
                    white: bool = False, holdout_every: int = 8, train_views: int | None = None,
                    eval_views: int | None = None) -> GridScene:
    """An INRIA model folder and, optionally, its dataset.

    With ``data`` (NeRF-synthetic or instant-ngp, :func:`gsw.data.load_dataset`) the ``train`` split gives
    the embedding views and images and the ``test`` split the evaluation views; without it the model's
    ``cameras.json`` is split, every ``holdout_every``-th view held out (no images: FGD phase 1 then weighs
    the renders).

    Args:
        model: the INRIA model folder.
        data: its dataset, or None.
        downscale: image / camera size divisor.
        white: white background (NeRF-synthetic), else black.
        holdout_every: hold-out period where the data has no test split.
        train_views: use this many evenly spaced embedding views (default: all).
        eval_views: use the first this many evaluation views (default: all).

    Returns:
        A :class:`GridScene`.
    """
    from gsw.data import holdout_indices, load_dataset, load_inria_model

    bg = (1.0, 1.0, 1.0) if white else (0.0, 0.0, 0.0)
    m = load_inria_model(model, downscale=downscale)
    if data is None:
        train_idx, test_idx = holdout_indices(len(m.cameras), holdout_every)
        cams, held_out, images = [m.cameras[i] for i in train_idx], [m.cameras[i] for i in test_idx], None
    else:
        kw = dict(downscale=downscale, background=bg, holdout_every=holdout_every)
        train, test = load_dataset(data, "train", **kw), load_dataset(data, "test", **kw)
        cams, held_out, images = train.cameras, test.cameras, train.images
    idx = _spread(len(cams), train_views, "train_views")
    held_out = _first(held_out, eval_views, "eval_views")
    key = dict(kind="inria", model=str(Path(model).resolve()), data=None if data is None else str(Path(data).resolve()),
               downscale=downscale, white=white, holdout_every=holdout_every, train_views=len(idx),
               eval_views=len(held_out))
    return GridScene(m.gaussians, [cams[i] for i in idx], held_out, None if images is None else images[idx], bg,
                     key)
