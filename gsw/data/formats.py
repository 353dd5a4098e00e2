"""Detection and loading of the COLMAP, LLFF and nerfstudio datasets (used by
:func:`gsw.data.loaders.detect_format` and :func:`gsw.data.loaders.load_dataset`).

Detection, first match wins: a ``transforms.json`` with a ``camera_model`` key is nerfstudio; a folder with
``cameras.{bin,txt}`` in itself, ``sparse/0`` or ``sparse`` is COLMAP (also when it holds ``poses_bounds.npy``:
the COLMAP model carries the principal point and distortion); a folder with ``poses_bounds.npy`` is LLFF.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from gsw.data.colmap import load_colmap
from gsw.data.colmap_io import find_colmap_model
from gsw.data.llff import load_llff
from gsw.data.loaders import Dataset
from gsw.data.nerfstudio import is_nerfstudio_transforms, load_nerfstudio

__all__ = ["EXTRA_FORMATS", "SUPPORTED_DATASETS", "detect_extra_format", "load_extra_dataset"]

EXTRA_FORMATS = ("colmap", "llff", "nerfstudio")
"""Formats handled here."""

SUPPORTED_DATASETS = (
    "transforms_train.json (NeRF-synthetic), transforms.json (instant-ngp, or nerfstudio with camera_model), "
    "sparse/0/ or sparse/ + images/ (COLMAP), poses_bounds.npy + images/ (LLFF) or cameras.json + point_cloud/ "
    "(INRIA model folder)"
)
"""What a dataset folder may hold, for error messages."""


def detect_extra_format(path: str | os.PathLike) -> str | None:
    """``"nerfstudio"``, ``"colmap"`` or ``"llff"`` for an existing path, or ``None`` when it is none of them."""
    path = Path(path)
    if path.is_file():
        if path.name == "transforms.json" and is_nerfstudio_transforms(path):
            return "nerfstudio"
        return "llff" if path.name == "poses_bounds.npy" else None
    if (path / "transforms.json").is_file() and is_nerfstudio_transforms(path / "transforms.json"):
        return "nerfstudio"
    if find_colmap_model(path) is not None:
        return "colmap"
    if (path / "poses_bounds.npy").is_file():
        return "llff"
    return None


def load_extra_dataset(fmt: str, path: str | os.PathLike, split: str, *, downscale: float, background: Any,
                       holdout_every: int, undistort: bool, images_dir: str | os.PathLike | None) -> Dataset:
    """Load a dataset of one of :data:`EXTRA_FORMATS` with :func:`gsw.data.load_dataset`'s arguments.

    ``images_dir`` applies to COLMAP and LLFF; ``undistort`` to COLMAP and nerfstudio.
    """
    path = Path(path)
    if fmt == "colmap":
        return load_colmap(path, split, downscale=downscale, background=background, holdout_every=holdout_every,
                           undistort=undistort, images_dir=images_dir)
    if fmt == "llff":
        return load_llff(path.parent if path.is_file() else path, split, downscale=downscale, background=background,
                         holdout_every=holdout_every, images_dir=images_dir)
    if fmt == "nerfstudio":
        return load_nerfstudio(path, split, downscale=downscale, background=background, undistort=undistort,
                               holdout_every=holdout_every)
    raise ValueError(f"unknown dataset format {fmt!r}; these loaders handle {', '.join(EXTRA_FORMATS)}")
