"""The tile assignment of the reference rasterizer: which tiles a splat is binned to (``csrc/core/tiles.h``).

A splat goes to the tiles of its radius rectangle (:func:`reference_tile_rects`) that hold a pixel centre inside
its opacity-aware skip ellipse (widened by bounds of the kernels' rounding); every row of tiles is cut to the x
span of the ellipse over the row. The arithmetic mirrors ``tile_footprint`` / ``footprint_row`` operation by
operation (one rounding each, same order), so the decisions equal the C++ binning's.
"""

from __future__ import annotations

import torch

from gsw import constants as K
from gsw._ext import _C
from gsw.render._reference.project import _c, reference_tile_rects

__all__ = ["reference_tile_spans"]

#: Pixel margin of the tile assignment's coordinates, and the largest pixel radius (csrc/core/constants.h).
BIN_MARGIN: float = float(_C.constants["BIN_MARGIN"])
MAX_RADIUS: int = int(_C.constants["MAX_RADIUS"])


def _where_lt(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``x < y ? x : y``."""
    return torch.where(x < y, x, y)


def _where_gt(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``x > y ? x : y``."""
    return torch.where(x > y, x, y)


def _centre_tile_span(lo: torch.Tensor, hi: torch.Tensor, t0: torch.Tensor,
                      t1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``centre_tile_span``: tiles [a, b) of the pixel centres in [lo, hi], clamped to [t0, t1) (floats in, floats out)."""
    half, inv_ts, one = _c(0.5, lo), _c(1.0 / K.TILE_SIZE, lo), _c(1.0, lo)
    fa = torch.floor(torch.ceil(lo - half) * inv_ts)
    fb = torch.floor(torch.floor(hi - half) * inv_ts) + one
    a = torch.where(fa > t0, torch.where(fa < t1, fa, t1), t0)
    b = torch.where(fb < t1, torch.where(fb > a, fb, a), t1)
    return a, b


def _chord(v: torch.Tensor, mx: torch.Tensor, inv_a: torch.Tensor, b: torch.Tensor, r2a: torch.Tensor,
           det: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``footprint_chord``: the x interval of the ellipse at row offset ``v``."""
    disc = r2a - det * (v * v)
    s = torch.sqrt(torch.where(disc > 0, disc, torch.zeros_like(disc)))
    bv = b * v
    return mx - (bv + s) * inv_a, mx - (bv - s) * inv_a


def _ellipse(m: torch.Tensor, con: torch.Tensor, skip: torch.Tensor,
             radii: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``tile_footprint``'s ellipse: (ok, 1 / a, b, a R2, det, ex, ey, margin, vstar, slack), each [N] in ``m``'s dtype."""
    eps = _c(torch.finfo(m.dtype).eps, m)
    a, b, c = con[:, 0], con[:, 1], con[:, 2]
    ac, bb = a * c, b * b
    det = (ac - bb) - (_c(4.0, m) * eps) * (ac + bb)
    reach = radii.to(m.dtype) + _c(2.0 * K.TILE_SIZE, m)
    spread = (torch.abs(a) + torch.abs(c)) + _c(2.0, m) * torch.abs(b)
    tol = ((_c(8.0, m) * eps) * spread) * (reach * reach)
    one_plus = _c(1.0 + 16.0 * float(torch.finfo(m.dtype).eps), m)
    r2 = (_c(-2.0, m) * skip + tol) * one_plus
    r2_det = r2 / det
    ex = torch.sqrt(r2_det * c)
    ey = torch.sqrt(r2_det * a)
    big = _c(float(MAX_RADIUS), m)
    ok = (a > 0) & (c > 0) & (det > 0) & (ex <= big) & (ey <= big)
    extent = (torch.abs(m[:, 0]) + torch.abs(m[:, 1])) + (ex + ey)
    margin = _c(BIN_MARGIN, m) + (_c(8.0, m) * eps) * extent
    return ok, _c(1.0, m) / a, b, a * r2, det, ex, ey, margin, (b * ex) / c, _c(1e-3, m) * (ey + _c(1.0, m))


@torch.no_grad()
def reference_tile_spans(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, radii: torch.Tensor,
                         width: int, height: int) -> torch.Tensor:
    """The tiles each splat is binned to, as ``tile_footprint`` / ``footprint_row`` (not differentiated).

    Args:
        means2d: [N, 2] projected centres (pixels).
        conics: [N, 3] inverse 2-D covariances (a, b, c).
        opacities: [N] opacities.
        radii: [N] integer pixel radii, 0 = culled.
        width: image width in pixels.
        height: image height in pixels.

    Returns:
        [N, tiles_y, 2] int32: per tile row, the half-open range [x_a, x_b) of tile columns (empty: equal ends).
    """
    m, con, op = means2d.detach(), conics.detach(), opacities.detach()
    tiles_y = (height + K.TILE_SIZE - 1) // K.TILE_SIZE
    rects = reference_tile_rects(m, radii, width, height).to(m.dtype)
    x0, y0, x1, y1 = rects.unbind(-1)
    skip = torch.log(_c(K.ALPHA_MIN, m) / op) - _c(K.SKIP_LOG_MARGIN, m)
    some = (radii > 0) & ((x1 - x0) * (y1 - y0) > 0) & ~(skip >= 0)
    ok, inv_a, b, r2a, det, ex, ey, margin, vstar, slack = _ellipse(m, con, skip, radii)
    mx, my = m[:, 0], m[:, 1]
    ey0, ey1 = _centre_tile_span((my - ey) - margin, (my + ey) + margin, y0, y1)
    ex0, ex1 = _centre_tile_span((mx - ex) - margin, (mx + ex) + margin, x0, x1)
    y0, y1 = torch.where(ok, ey0, y0), torch.where(ok, ey1, y1)
    x0, x1 = torch.where(ok, ex0, x0), torch.where(ok, ex1, x1)
    some = some & (x0 < x1) & (y0 < y1)
    # Rows: [N, tiles_y] (column vectors broadcast over the rows).
    ty = torch.arange(tiles_y, device=m.device, dtype=m.dtype)[None, :]
    col = [t[:, None] for t in (mx, my, inv_a, b, r2a, det, ex, ey, margin, vstar, slack, x0, x1)]
    mx_, my_, inv_a_, b_, r2a_, det_, ex_, ey_, margin_, vstar_, slack_, x0_, x1_ = col
    top = ty * _c(float(K.TILE_SIZE), m) + _c(0.5, m)
    bottom = ty * _c(float(K.TILE_SIZE), m) + _c(K.TILE_SIZE - 0.5, m)
    d_top, d_bottom = top - my_, bottom - my_
    vlo = torch.where(d_top < -ey_, -ey_, torch.where(d_top > ey_, ey_, d_top))
    vhi = torch.where(d_bottom < -ey_, -ey_, torch.where(d_bottom > ey_, ey_, d_bottom))
    l0, h0 = _chord(vlo, mx_, inv_a_, b_, r2a_, det_)
    l1, h1 = _chord(vhi, mx_, inv_a_, b_, r2a_, det_)
    lo, hi = _where_lt(l0, l1), _where_gt(h0, h1)
    band_lo, band_hi = vlo - slack_, vhi + slack_
    lo = torch.where((vstar_ >= band_lo) & (vstar_ <= band_hi), mx_ - ex_, lo)
    hi = torch.where((-vstar_ >= band_lo) & (-vstar_ <= band_hi), mx_ + ex_, hi)
    xa, xb = _centre_tile_span(lo - margin_, hi + margin_, x0_, x1_)
    xa = torch.where(ok[:, None], xa, x0_.expand_as(xa))
    xb = torch.where(ok[:, None], xb, x1_.expand_as(xb))
    in_rows = some[:, None] & (ty >= y0[:, None]) & (ty < y1[:, None])
    zero = torch.zeros_like(xa)
    spans = torch.stack([torch.where(in_rows, xa, zero), torch.where(in_rows, xb, zero)], dim=-1)
    return spans.to(torch.int32)
