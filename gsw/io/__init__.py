"""File formats for 3DGS models: INRIA PLY, PlayCanvas compressed PLY, antimatter15 ``.splat``, Niantic ``.spz``
and (read only) gsplat / splatfacto checkpoints; :func:`load_gaussians` / :func:`save_gaussians` pick the format
(see :mod:`gsw.io.formats`).

Example:
    >>> from gsw.io import load_gaussians, save_ply
    >>> g = load_gaussians("point_cloud.ply")  # doctest: +SKIP
"""

from __future__ import annotations

import os

from gsw.gaussians import Gaussians
from gsw.io.checkpoint import CheckpointError, load_checkpoint
from gsw.io.compressed_ply import CompressedPlyError, load_compressed_ply, save_compressed_ply
from gsw.io.formats import MODEL_FORMATS, WRITABLE_FORMATS, load_model, model_format, save_model
from gsw.io.ply import PlyError, load_ply, ply_property_names, save_ply
from gsw.io.splat import SplatError, load_splat, save_splat
from gsw.io.spz import SpzError, load_spz, save_spz

__all__ = [
    "PlyError", "SplatError", "load_ply", "save_ply", "ply_property_names", "load_splat", "save_splat",
    "load_gaussians", "save_gaussians",
    "CheckpointError", "CompressedPlyError", "SpzError", "load_checkpoint", "load_compressed_ply",
    "save_compressed_ply", "load_spz", "save_spz", "MODEL_FORMATS", "WRITABLE_FORMATS", "model_format",
    "load_model", "save_model",
]


def load_gaussians(path: str | os.PathLike) -> Gaussians:
    """Load a model, choosing the reader by extension (and a ``.ply``'s header), see :func:`load_model`.

    Args:
        path: the model file (``.ply``, ``.compressed.ply``, ``.splat``, ``.spz``, ``.pt``/``.ckpt``).

    Returns:
        The model on the CPU in float32.

    Raises:
        ValueError: for an unknown extension (naming the supported ones); the format's error
            (:class:`PlyError`, :class:`SplatError`, :class:`SpzError`, ...) for a malformed file.
    """
    return load_model(path)


def save_gaussians(gaussians: Gaussians, path: str | os.PathLike) -> None:
    """Save a model, choosing the writer by extension (``.ply``, ``.compressed.ply``, ``.splat``, ``.spz``),
    atomically; see :func:`save_model`.

    Args:
        gaussians: the model.
        path: destination file.
    """
    save_model(gaussians, path)
