"""Read and write the antimatter15 ``.splat`` format (web viewers).

Each splat is 32 little-endian bytes, no header::

    bytes  0..11  position x, y, z            float32, world
    bytes 12..23  scale x, y, z               float32, linear standard deviations (not log)
    bytes 24..27  colour r, g, b, alpha       uint8, round(255 * value)
    bytes 28..31  rotation w, x, y, z         uint8, round(128 * q / |q| + 128) clamped to 0..255

The format stores only the view-independent colour, so models load as SH degree 0 and writing drops
``f_rest``. Conversions:

- ``rgb`` and ``f_dc`` by :func:`gsw.gaussians.sh_dc_to_rgb` / :func:`gsw.gaussians.rgb_to_sh_dc`,
- ``alpha = sigmoid(opacity_logit)`` and back ``logit(clamp(alpha, eps, 1 - eps))`` with
  ``eps = 1e-6`` (below half a quantisation step, so alpha bytes 0 and 255 survive a round trip),
- ``log_scales = log(scale)``.

The format has no header or magic number, so any file of 32k bytes would decode. Reading and writing
therefore apply the same sanity check (:func:`check_splat_records`): positions finite with
``|x| <= MAX_ABS_POSITION``, scales finite in ``SCALE_RANGE``, and rotation bytes not all 128 (a zero
quaternion). Random bytes fail it (a random float32 is NaN, huge, tiny or negative far too often), and
whatever :func:`save_splat` writes passes it, so a written file always loads back. Writing raises scales
below ``SCALE_RANGE[0]`` to it: 3DGS training leaves some splats flat, with an axis of 1e-11 or less, and a
standard deviation of 1e-10 instead renders the same (the rasteriser's 0.3 px low-pass dominates).

Quantisation uses rounding to nearest; this matches the fixture in ``shared/data/ply/sh3_fixture``
(antimatter15's original ``convert.py`` truncates instead, at most one step of difference).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from gsw._atomic import atomic_write
from gsw.gaussians import Gaussians, rgb_to_sh_dc, sh_dc_to_rgb

__all__ = [
    "SplatError", "load_splat", "save_splat", "check_splat_records", "SPLAT_DTYPE", "ALPHA_EPS",
    "MAX_ABS_POSITION", "SCALE_RANGE",
]

SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
"""numpy structured dtype of one 32-byte splat record."""

ALPHA_EPS = 1e-6
"""Alpha is clamped to ``[ALPHA_EPS, 1 - ALPHA_EPS]`` before the logit."""

MAX_ABS_POSITION = 1e7
"""Largest accepted ``|x|``, ``|y|``, ``|z|`` of a position (float32 has a 1-unit resolution at 1.7e7)."""

SCALE_RANGE = (1e-10, 1e7)
"""Accepted range of the linear scales (standard deviations), both ends included."""

assert SPLAT_DTYPE.itemsize == 32


class SplatError(ValueError):
    """A ``.splat`` file is malformed."""


def check_splat_records(records: np.ndarray, what: str) -> None:
    """Raise :class:`SplatError` unless every record passes the sanity check of the module docstring.

    Args:
        records: ``[N]`` array of :data:`SPLAT_DTYPE`.
        what: prefix of the message (the file, or "refusing to write <file>").

    Raises:
        SplatError: naming each failed check, how many splats fail it and the first one.
    """
    with np.errstate(invalid="ignore"):  # signalling NaNs in random bytes
        position, scale = records["position"].astype(np.float64), records["scale"].astype(np.float64)
        checks = {
            "non-finite position": ~np.isfinite(position).all(1),
            f"position beyond +-{MAX_ABS_POSITION:g}": (np.abs(position) > MAX_ABS_POSITION).any(1),
            "non-finite scale": ~np.isfinite(scale).all(1),
            f"scale outside [{SCALE_RANGE[0]:g}, {SCALE_RANGE[1]:g}]":
                ((scale < SCALE_RANGE[0]) | (scale > SCALE_RANGE[1])).any(1),
            "zero quaternion (rotation bytes all 128)": (records["rot"] == 128).all(1),
        }
    problems = []
    for name, bad in checks.items():
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            problems.append(
                f"{int(bad.sum())} of {len(records)} splats have a {name} (first: splat {i}, position "
                f"{position[i].tolist()}, scale {scale[i].tolist()}, rotation bytes {records['rot'][i].tolist()})"
            )
    if problems:
        raise SplatError(f"{what}: " + "; ".join(problems))


def load_splat(path: str | os.PathLike) -> Gaussians:
    """Load an antimatter15 ``.splat`` file.

    Args:
        path: the ``.splat`` file.

    Returns:
        :class:`~gsw.gaussians.Gaussians` on the CPU in float32 with SH degree 0, in file order. Quaternions
        are the decoded bytes ``(b - 128) / 128`` (unit length up to quantisation).

    Raises:
        SplatError: the path is a directory, the file is empty, its size is not a multiple of 32 bytes, or
            a record fails :func:`check_splat_records` (not a ``.splat`` file, or a corrupted one).
        FileNotFoundError: the file does not exist.
    """
    path = Path(path)
    if path.is_dir():
        raise SplatError(f"{path}: is a directory, not a .splat file")
    size = path.stat().st_size
    if size == 0:
        raise SplatError(f"{path}: empty file (0 splats)")
    if size % SPLAT_DTYPE.itemsize:
        raise SplatError(
            f"{path}: file size {size} bytes is not a multiple of {SPLAT_DTYPE.itemsize} (bytes per splat); "
            "not a .splat file or truncated"
        )
    records = np.fromfile(path, dtype=SPLAT_DTYPE)
    check_splat_records(records, f"{path}: not a plausible .splat file")
    n = len(records)
    rgba = torch.from_numpy(records["rgba"].astype(np.float64)) / 255.0
    rot = torch.from_numpy(records["rot"].astype(np.float64))
    alpha = rgba[:, 3].clamp(ALPHA_EPS, 1.0 - ALPHA_EPS)
    return Gaussians(
        means=torch.from_numpy(records["position"].astype(np.float32)),
        log_scales=torch.from_numpy(records["scale"].astype(np.float64)).log().float(),
        quats=((rot - 128.0) / 128.0).float(),
        opacity_logits=torch.logit(alpha).float(),
        sh=rgb_to_sh_dc(rgba[:, :3]).float().reshape(n, 1, 3),
    )


def splat_sort_order(gaussians: Gaussians) -> torch.Tensor:
    """antimatter15's ordering: decreasing ``prod(scales) * opacity`` (big, opaque splats first).

    Args:
        gaussians: the model.

    Returns:
        ``[N]`` int64 permutation.
    """
    key = gaussians.log_scales.detach().double().sum(1).exp() * gaussians.opacities.detach().double()
    return torch.argsort(key, descending=True, stable=True)


def save_splat(gaussians: Gaussians, path: str | os.PathLike, *, sort: bool = False) -> None:
    """Write a model as an antimatter15 ``.splat`` file, atomically.

    Only the DC colour is kept (``f_rest`` is dropped); colours are clamped to ``[0, 1]``; scales below
    ``SCALE_RANGE[0]`` (flat splats) are written as ``SCALE_RANGE[0]`` (see the module docstring).

    Args:
        gaussians: the model (any device/dtype/SH degree).
        path: destination file; its directory must exist.
        sort: reorder like antimatter15's converter (see :func:`splat_sort_order`), which lets web viewers
            show the most important splats first. By default the model order is kept, so that
            ``load_splat(save_splat(g))[i]`` corresponds to ``g[i]``.

    Raises:
        SplatError: if the model is empty, holds NaN/Inf values or a Gaussian fails
            :func:`check_splat_records` (which :func:`load_splat` applies, so every file written loads back).
    """
    g = gaussians.detach().to(device="cpu", dtype=torch.float64)
    if g.num_gaussians == 0:
        raise SplatError(f"refusing to write {path}: the model has 0 Gaussians (an empty .splat cannot be read)")
    try:
        g.check_finite()
    except ValueError as exc:
        raise SplatError(f"refusing to write {path}: {exc}") from None
    if sort:
        g = g[splat_sort_order(g)]
    rgb = sh_dc_to_rgb(g.sh[:, 0])
    rgba = torch.cat([rgb, g.opacities[:, None]], dim=1)
    records = np.empty(g.num_gaussians, dtype=SPLAT_DTYPE)
    records["position"] = g.means.numpy()
    with np.errstate(over="ignore"):  # beyond float32: inf, reported by the check below
        records["scale"] = np.maximum(g.scales.numpy(), SCALE_RANGE[0])  # flat splats: see the module docstring
    records["rgba"] = _quantise(rgba.numpy() * 255.0)
    records["rot"] = _quantise(g.rotations.numpy() * 128.0 + 128.0)
    check_splat_records(records, f"refusing to write {path}")
    with atomic_write(path, "wb") as f:
        f.write(records.tobytes())


def _quantise(values: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(values), 0, 255).astype(np.uint8)
