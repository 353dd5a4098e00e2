"""The :class:`Dataset` container, :class:`DatasetError` and the checks every dataset loader shares.

Loaders (:mod:`gsw.data.loaders`, :mod:`gsw.data.inria`) check their inputs and never silently adapt them:
every missing image is named in one error, image read errors name the view, and views smaller than
:data:`MIN_IMAGE_SIZE` pixels on a side are rejected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.camera_io import json_number, read_json
from gsw.data.images import IMAGE_SUFFIXES, read_image

__all__ = ["Dataset", "DatasetError", "MIN_IMAGE_SIZE"]

MIN_IMAGE_SIZE = 4
"""Smallest usable training view side, pixels: the watermark decoder reads the level-2 wavelet subband
(``H/4 x W/4``), which is empty below 4 pixels."""

Background = Sequence[float] | Tensor


class DatasetError(ValueError):
    """A dataset is missing files, malformed, inconsistent or of an unknown format."""


@dataclass
class Dataset:
    """Posed images.

    Attributes:
        cameras: ``V`` cameras.
        images: ``[V, 3, H, W]`` float32 in ``[0, 1]`` (composited on :attr:`background` where the files had
            alpha).
        alphas: ``[V, 1, H, W]`` alpha masks, or ``None`` when the images had no alpha channel.
        names: ``V`` image names (relative file paths without extension for NeRF-style datasets).
        background: ``[3]`` RGB background the images were composited on.
        format: ``"nerf_synthetic"``, ``"instant_ngp"`` or ``"inria"``.
        points: optional ``[P, 3]`` point cloud for initialisation.
        point_colors: optional ``[P, 3]`` RGB in ``[0, 1]`` of :attr:`points`.
        meta: format-specific extras (e.g. instant-ngp ``aabb_scale``).
    """

    cameras: list[Camera]
    images: Tensor
    alphas: Tensor | None
    names: list[str]
    background: Tensor
    format: str = ""
    points: Tensor | None = None
    point_colors: Tensor | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        v = len(self.cameras)
        if self.images.dim() != 4 or self.images.shape[0] != v or self.images.shape[1] != 3:
            raise DatasetError(f"images must be [V={v}, 3, H, W], got {list(self.images.shape)}")
        if len(self.names) != v:
            raise DatasetError(f"{len(self.names)} names for {v} cameras")
        h, w = self.images.shape[-2:]
        for cam in self.cameras:
            if (cam.height, cam.width) != (h, w):
                raise DatasetError(f"camera {cam.name!r} is {cam.width}x{cam.height} but images are {w}x{h}")
        if self.alphas is not None and tuple(self.alphas.shape) != (v, 1, h, w):
            raise DatasetError(f"alphas must be [V, 1, H, W] = {[v, 1, h, w]}, got {list(self.alphas.shape)}")

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def height(self) -> int:
        """Image height ``H``."""
        return int(self.images.shape[-2])

    @property
    def width(self) -> int:
        """Image width ``W``."""
        return int(self.images.shape[-1])

    def subset(self, indices: Sequence[int]) -> "Dataset":
        """The views at ``indices`` (a new :class:`Dataset` sharing the point cloud)."""
        idx = list(indices)
        return Dataset(
            cameras=[self.cameras[i] for i in idx], images=self.images[idx],
            alphas=None if self.alphas is None else self.alphas[idx], names=[self.names[i] for i in idx],
            background=self.background, format=self.format, points=self.points, point_colors=self.point_colors,
            meta=dict(self.meta))


# ------------------------------------------------------------------------------------------- helpers


def _background(background: Background) -> Tensor:
    bg = torch.as_tensor(background, dtype=torch.float32).detach().cpu().flatten()
    if bg.shape != (3,) or not torch.isfinite(bg).all():
        raise ValueError(f"background must be 3 finite numbers, got {background!r}")
    return bg


def _check_downscale(downscale: float) -> float:
    if isinstance(downscale, bool) or not isinstance(downscale, (int, float)) or not downscale >= 1 \
            or not math.isfinite(downscale):
        raise ValueError(f"downscale must be a number >= 1, got {downscale!r}")
    return float(downscale)


def _read_json(path: Path) -> Any:
    return read_json(path, DatasetError)


def _find_image(root: Path, file_path: str) -> Path | None:
    """The image file for a name with or without its extension, or ``None``."""
    p = Path(file_path)
    path = p if p.is_absolute() else root / p
    if path.suffix in IMAGE_SUFFIXES and path.is_file():
        return path
    for suffix in IMAGE_SUFFIXES:
        candidate = path.with_name(path.name + suffix)
        if candidate.is_file():
            return candidate
    return path if path.is_file() else None


def _find_images(root: Path, names: Sequence[str], context: str) -> list[Path]:
    """Every image of ``names``; one error naming all the missing ones."""
    found = [_find_image(root, name) for name in names]
    missing = [str(root / name) for name, path in zip(names, found) if path is None]
    if missing:
        shown = ", ".join(missing[:10]) + (f", ... ({len(missing) - 10} more)" if len(missing) > 10 else "")
        raise DatasetError(f"{context}: {len(missing)} image{'s' if len(missing) > 1 else ''} not found: {shown} "
                           f"(also tried {'/'.join(s for s in IMAGE_SUFFIXES if s.islower())})")
    return [p for p in found if p is not None]


def _read_view(path: Path, context: str) -> Tensor:
    """``read_image`` with errors as :class:`DatasetError` naming the view."""
    try:
        return read_image(path)
    except (ValueError, FileNotFoundError) as exc:
        raise DatasetError(f"{context}: {exc}") from None


def _check_usable(width: int, height: int, context: str) -> None:
    if min(width, height) < MIN_IMAGE_SIZE:
        raise DatasetError(f"{context}: a {width}x{height} view is too small to train on "
                           f"(at least {MIN_IMAGE_SIZE} pixels on a side)")


def _number(obj: dict, key: str, context: str, default: Any = None, positive: bool = False) -> Any:
    return json_number(obj, key, context, default, error=DatasetError, positive=positive)
