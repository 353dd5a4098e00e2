"""Read and write the antimatter15 ``.splat`` format (web viewers).

Each splat is 32 little-endian bytes, no header::

    bytes  0..11  position x, y, z            float32, world
    bytes 12..23  scale x, y, z               float32, linear standard deviations (not log)
    bytes 24..27  colour r, g, b, alpha       uint8, round(255 * value)
    bytes 28..31  rotation w, x, y, z         uint8, round(128 * q / |q| + 128) clamped to 0..255

The format stores only the view-independent colour, so models load as SH degree 0 and writing drops
``f_rest``. Conversions (``SH_C0`` and ``SH_COLOR_OFFSET`` from :mod:`gsw.constants`):

- ``rgb = SH_COLOR_OFFSET + SH_C0 * f_dc`` and back ``f_dc = (rgb - SH_COLOR_OFFSET) / SH_C0``,
- ``alpha = sigmoid(opacity_logit)`` and back ``logit(clamp(alpha, eps, 1 - eps))`` with
  ``eps = 1e-6`` (below half a quantisation step, so alpha bytes 0 and 255 survive a round trip),
- ``log_scales = log(scale)`` (a zero scale becomes the log of the smallest positive float32).

Quantisation uses rounding to nearest; this matches the fixture in ``shared/data/ply/sh3_fixture``
(antimatter15's original ``convert.py`` truncates instead, at most one step of difference).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from gsw._atomic import atomic_write
from gsw.constants import SH_C0, SH_COLOR_OFFSET
from gsw.gaussians import Gaussians

__all__ = ["SplatError", "load_splat", "save_splat", "SPLAT_DTYPE", "ALPHA_EPS"]

SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
"""numpy structured dtype of one 32-byte splat record."""

ALPHA_EPS = 1e-6
"""Alpha is clamped to ``[ALPHA_EPS, 1 - ALPHA_EPS]`` before the logit."""

assert SPLAT_DTYPE.itemsize == 32


class SplatError(ValueError):
    """A ``.splat`` file is malformed."""


def load_splat(path: str | os.PathLike) -> Gaussians:
    """Load an antimatter15 ``.splat`` file.

    Args:
        path: the ``.splat`` file.

    Returns:
        :class:`~gsw.gaussians.Gaussians` on the CPU in float32 with SH degree 0, in file order. Quaternions
        are the decoded bytes ``(b - 128) / 128`` (unit length up to quantisation).

    Raises:
        SplatError: the file size is not a multiple of 32 bytes or positions/scales are not finite.
    """
    path = Path(path)
    size = path.stat().st_size
    if size % SPLAT_DTYPE.itemsize:
        raise SplatError(
            f"{path}: file size {size} bytes is not a multiple of {SPLAT_DTYPE.itemsize} (bytes per splat); "
            "not a .splat file or truncated"
        )
    records = np.fromfile(path, dtype=SPLAT_DTYPE)
    n = len(records)
    bad = ~np.isfinite(records["position"]).all(1) | ~np.isfinite(records["scale"]).all(1)
    if bad.any():
        raise SplatError(f"{path}: {int(bad.sum())} splats have non-finite positions or scales")

    means = torch.from_numpy(records["position"].astype(np.float32))
    scales = torch.from_numpy(records["scale"].astype(np.float64))
    rgba = torch.from_numpy(records["rgba"].astype(np.float64)) / 255.0
    rot = torch.from_numpy(records["rot"].astype(np.float64))

    tiny = float(np.finfo(np.float32).tiny)
    log_scales = scales.abs().clamp_min(tiny).log()
    alpha = rgba[:, 3].clamp(ALPHA_EPS, 1.0 - ALPHA_EPS)
    f_dc = (rgba[:, :3] - SH_COLOR_OFFSET) / SH_C0
    return Gaussians(
        means=means,
        log_scales=log_scales.float(),
        quats=((rot - 128.0) / 128.0).float(),
        opacity_logits=torch.logit(alpha).float(),
        sh=f_dc.float().reshape(n, 1, 3),
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

    Only the DC colour is kept (``f_rest`` is dropped); colours are clamped to ``[0, 1]``.

    Args:
        gaussians: the model (any device/dtype/SH degree).
        path: destination file; its directory must exist.
        sort: reorder like antimatter15's converter (see :func:`splat_sort_order`), which lets web viewers
            show the most important splats first. By default the model order is kept, so that
            ``load_splat(save_splat(g))[i]`` corresponds to ``g[i]``.

    Raises:
        SplatError: if the model holds NaN/Inf values.
    """
    g = gaussians.detach().to(device="cpu", dtype=torch.float64)
    try:
        g.check_finite()
    except ValueError as exc:
        raise SplatError(f"refusing to write {path}: {exc}") from None
    if sort:
        g = g[splat_sort_order(g)]
    rgb = SH_COLOR_OFFSET + SH_C0 * g.sh[:, 0]
    rgba = torch.cat([rgb, g.opacities[:, None]], dim=1)
    records = np.empty(g.num_gaussians, dtype=SPLAT_DTYPE)
    records["position"] = g.means.numpy()
    records["scale"] = g.scales.numpy()
    records["rgba"] = _quantise(rgba.numpy() * 255.0)
    records["rot"] = _quantise(g.rotations.numpy() * 128.0 + 128.0)
    with atomic_write(path, "wb") as f:
        f.write(records.tobytes())


def _quantise(values: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(values), 0, 255).astype(np.uint8)
