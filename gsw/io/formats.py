"""Choosing a model reader/writer: by file extension, and for ``.ply`` by its header.

Formats (names as used by :func:`load_model`, :func:`save_model` and ``gsw export --format``):

========================  ==========================  ==================================================
name                      files                       module
========================  ==========================  ==================================================
``ply``                   ``*.ply`` (INRIA layout)    :mod:`gsw.io.ply`
``compressed-ply``        ``*.ply`` with a ``chunk``  :mod:`gsw.io.compressed_ply` (written for
                          element                     ``*.compressed.ply``)
``splat``                 ``*.splat``                 :mod:`gsw.io.splat`
``spz``                   ``*.spz``                   :mod:`gsw.io.spz`
``checkpoint`` (read)     ``*.pt``, ``*.ckpt``        :mod:`gsw.io.checkpoint` (gsplat, splatfacto)
========================  ==========================  ==================================================
"""

from __future__ import annotations

import os
from pathlib import Path

from gsw.gaussians import Gaussians
from gsw.io.checkpoint import load_checkpoint
from gsw.io.compressed_ply import is_compressed_ply, load_compressed_ply, save_compressed_ply
from gsw.io.ply import load_ply, save_ply
from gsw.io.splat import load_splat, save_splat
from gsw.io.spz import load_spz, save_spz

__all__ = ["MODEL_FORMATS", "WRITABLE_FORMATS", "model_format", "load_model", "save_model"]

MODEL_FORMATS = ("ply", "compressed-ply", "splat", "spz", "checkpoint")
"""Every format :func:`load_model` reads."""

WRITABLE_FORMATS = ("ply", "compressed-ply", "splat", "spz")
"""Every format :func:`save_model` writes."""

_SUFFIXES = {".splat": "splat", ".spz": "spz", ".pt": "checkpoint", ".ckpt": "checkpoint"}
_READERS = {"ply": load_ply, "compressed-ply": load_compressed_ply, "splat": load_splat, "spz": load_spz,
            "checkpoint": load_checkpoint}
_WRITERS = {"ply": save_ply, "compressed-ply": save_compressed_ply, "splat": save_splat, "spz": save_spz}
_SUPPORTED = (".ply (INRIA or PlayCanvas compressed), .compressed.ply, .splat, .spz, "
              ".pt/.ckpt (gsplat / splatfacto checkpoints, read only)")


def model_format(path: str | os.PathLike, *, for_writing: bool = False) -> str:
    """The format of a model file, from its name (and, for an existing ``.ply`` being read, its header).

    Args:
        path: the file.
        for_writing: name the format to write (``*.compressed.ply`` -> ``compressed-ply``, other ``*.ply`` ->
            ``ply``) instead of sniffing an existing file's header.

    Returns:
        One of :data:`MODEL_FORMATS`.

    Raises:
        ValueError: an unknown extension (the message lists the supported ones).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        if not for_writing and path.is_file():
            return "compressed-ply" if is_compressed_ply(path) else "ply"
        return "compressed-ply" if path.name.lower().endswith(".compressed.ply") else "ply"
    if suffix in _SUFFIXES:
        return _SUFFIXES[suffix]
    raise ValueError(f"{path}: unknown model file extension {suffix!r}; supported: {_SUPPORTED}")


def load_model(path: str | os.PathLike, format: str | None = None) -> Gaussians:  # noqa: A002
    """Load a model in any supported format.

    Args:
        path: the model file.
        format: one of :data:`MODEL_FORMATS`; default from :func:`model_format`.

    Returns:
        The model on the CPU in float32.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unknown extension or format; the format's error (a ``ValueError`` subclass such as
            :class:`~gsw.io.ply.PlyError`) for a malformed file.
    """
    if format is not None and format not in _READERS:
        raise ValueError(f"unknown model format {format!r}; supported: {', '.join(MODEL_FORMATS)}")
    if not Path(path).exists():
        raise FileNotFoundError(f"{path}: no such model file")
    return _READERS[format or model_format(path)](path)


def save_model(gaussians: Gaussians, path: str | os.PathLike, format: str | None = None) -> None:  # noqa: A002
    """Save a model atomically in a writable format, with each writer's defaults.

    Args:
        gaussians: the model.
        path: destination file; its directory must exist.
        format: one of :data:`WRITABLE_FORMATS`; default from the name (``*.compressed.ply`` ->
            ``compressed-ply``).

    Raises:
        ValueError: unknown extension, or a format that cannot be written (checkpoints).
    """
    fmt = format or model_format(path, for_writing=True)
    if fmt not in WRITABLE_FORMATS:
        raise ValueError(f"{path}: cannot write {fmt!r} files; writable formats: {', '.join(WRITABLE_FORMATS)}")
    _WRITERS[fmt](gaussians, path)
