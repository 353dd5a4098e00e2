"""File formats for 3DGS models: INRIA PLY and antimatter15 ``.splat``.

Example:
    >>> from gsw.io import load_gaussians, save_ply
    >>> g = load_gaussians("point_cloud.ply")  # doctest: +SKIP
"""

from __future__ import annotations

import os
from pathlib import Path

from gsw.gaussians import Gaussians
from gsw.io.ply import PlyError, load_ply, ply_property_names, save_ply
from gsw.io.splat import SplatError, load_splat, save_splat

__all__ = [
    "PlyError", "SplatError", "load_ply", "save_ply", "ply_property_names", "load_splat", "save_splat",
    "load_gaussians", "save_gaussians",
]


def _suffix(path: str | os.PathLike) -> str:
    suffix = Path(path).suffix.lower()
    if suffix not in (".ply", ".splat"):
        raise ValueError(f"{path}: unknown model file extension {suffix!r} (expected .ply or .splat)")
    return suffix


def load_gaussians(path: str | os.PathLike) -> Gaussians:
    """Load a model, choosing the reader by extension (``.ply`` or ``.splat``).

    Args:
        path: the model file.

    Returns:
        The model on the CPU in float32.

    Raises:
        ValueError: for an unknown extension; :class:`PlyError`/:class:`SplatError` for a malformed file.
    """
    return load_ply(path) if _suffix(path) == ".ply" else load_splat(path)


def save_gaussians(gaussians: Gaussians, path: str | os.PathLike) -> None:
    """Save a model, choosing the writer by extension (``.ply`` or ``.splat``), atomically.

    Args:
        gaussians: the model.
        path: destination file.
    """
    if _suffix(path) == ".ply":
        save_ply(gaussians, path)
    else:
        save_splat(gaussians, path)
