"""Stage 2 of the reference rasterizer: 2-D splats -> image (the rasterization kernel's semantics).

See :mod:`gsw.render._reference` for the conventions (frames, masks, dtype, association order).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from gsw import constants as K
from gsw.render._reference.project import ReferenceProjection, _c, reference_project
from gsw.render._reference.tiles import reference_tile_spans

__all__ = ["ReferenceRender", "reference_rasterize_projected", "reference_rasterize", "reference_contribution"]


class ReferenceRender(NamedTuple):
    """Output of the blending stage (``RasterParams`` outputs plus reference extras).

    Attributes:
        image: [3, H, W] ``sum_i w_i color_i + final_T * background``.
        alpha: [1, H, W] ``1 - final_T``.
        depth: [1, H, W] ``sum_i w_i z_i`` (not normalised by alpha).
        final_T: [H, W] transmittance left after the last blended splat.
        n_blended: [H, W] int32 number of splats blended into each pixel.
        n_contrib: [H, W] int32 ``1 + index`` of the last blended splat in the pixel's tile
            list (the depth-sorted list of Gaussians binned to the pixel's tile, see
            :func:`reference_tile_spans`), 0 if none; same meaning as ``RasterParams::n_contrib``.
        weights: [N, H, W] blending weight ``w_i(p) = alpha_i(p) T_i(p)`` of every Gaussian at
            every pixel (0 where not blended), in the original Gaussian order.
        projection: the :class:`ReferenceProjection` when produced by
            :func:`reference_rasterize`, else None.
    """

    image: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    final_T: torch.Tensor
    n_blended: torch.Tensor
    n_contrib: torch.Tensor
    weights: torch.Tensor
    projection: ReferenceProjection | None = None


# ------------------------------------------------------------------ stage 2: blending


def _depth_order(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, depths: torch.Tensor,
                 radii: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The Gaussians that take part (binned to a tile), by ascending depth (ties by Gaussian index), and their tiles.

    Returns:
        (order [n] int64 indices, spans [N, tiles_y, 2] int32 from :func:`reference_tile_spans`).
    """
    spans = reference_tile_spans(means2d, conics, opacities, radii, width, height)
    active = (spans[:, :, 1] - spans[:, :, 0]).sum(dim=1) > 0
    idx = torch.nonzero(active).flatten()
    # stable sort of an index-ordered subset
    return idx[torch.sort(depths.detach()[idx], stable=True).indices], spans


def _pixel_grid(width: int, height: int, like: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Pixel centres (px, py) in ``like``'s dtype and tile coordinates (tx, ty), each [P], row-major."""
    jj, ii = torch.meshgrid(
        torch.arange(height, device=like.device), torch.arange(width, device=like.device), indexing="ij"
    )
    ii, jj = ii.flatten(), jj.flatten()
    half = _c(0.5, like)
    return ii.to(like.dtype) + half, jj.to(like.dtype) + half, ii // K.TILE_SIZE, jj // K.TILE_SIZE


def _chunk_alphas(order: torch.Tensor, spans: torch.Tensor, means2d: torch.Tensor, conics: torch.Tensor,
                  opacities: torch.Tensor, pixels: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
    """Alpha of every splat at every pixel of a chunk, with the masks of the blending rules.

    Args:
        order: [n] depth-sorted indices of the taking-part Gaussians.
        spans: [N, tiles_y, 2] tile column ranges per tile row (the binning).
        means2d: [N, 2] projected centres.
        conics: [N, 3] inverse 2-D covariances.
        opacities: [N] opacities.
        pixels: (px, py, tx, ty) of the chunk's pixels, each [Pc].

    Returns:
        (sub [m] Gaussians binned to a tile of the chunk, in depth order; part [m, Pc] the Gaussian is
        binned to the pixel's tile; alpha [m, Pc] (0 where not valid); valid [m, Pc] power <= 0 and
        alpha >= ALPHA_MIN in a binned tile).
    """
    px, py, tx, ty = pixels
    zero = torch.zeros((), dtype=means2d.dtype, device=means2d.device)
    alpha_max, alpha_min = _c(K.ALPHA_MAX, means2d), _c(K.ALPHA_MIN, means2d)
    s = spans[order][:, ty]  # [n, Pc, 2]: the span of each pixel's tile row
    part = (s[..., 0] <= tx) & (tx < s[..., 1])  # [n, Pc]
    keep = part.any(dim=1)
    sub, part = order[keep], part[keep]
    m2, con, op = means2d[sub], conics[sub], opacities[sub]
    dx = m2[:, 0:1] - px
    dy = m2[:, 1:2] - py
    a, b, c = con[:, 0:1], con[:, 1:2], con[:, 2:3]
    power = -_c(0.5, means2d) * (a * dx * dx + c * dy * dy) - b * dx * dy
    pos = power > 0
    g = torch.exp(torch.where(pos, zero, power))
    a_raw = op[:, None] * g
    alpha = torch.where(a_raw < alpha_max, a_raw, alpha_max)
    valid = part & ~pos & (alpha >= alpha_min)
    return sub, part, torch.where(valid, alpha, zero), valid


def _composite(sub: torch.Tensor, part: torch.Tensor, alpha: torch.Tensor, valid: torch.Tensor,
               colors: torch.Tensor, depths: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Front-to-back compositing of one chunk: the transmittance loop, one splat at a time.

    Args:
        sub, part, alpha, valid: as returned by :func:`_chunk_alphas` ([m], [m, Pc] each).
        colors: [N, 3] RGB.
        depths: [N] view-space depths.

    Returns:
        (C [3, Pc], D [Pc], T [Pc], n_blended [Pc] int32, n_contrib [Pc] int32, weights [N, Pc]).
    """
    dtype, device = alpha.dtype, alpha.device
    Pc = part.shape[1]
    zero, one, t_min = torch.zeros((), dtype=dtype, device=device), _c(1.0, alpha), _c(K.T_MIN, alpha)
    T = torch.ones(Pc, dtype=dtype, device=device)
    Cacc = torch.zeros(3, Pc, dtype=dtype, device=device)
    Dacc = torch.zeros(Pc, dtype=dtype, device=device)
    done = torch.zeros(Pc, dtype=torch.bool, device=device)
    n_bl = torch.zeros(Pc, dtype=torch.int32, device=device)
    n_co = torch.zeros(Pc, dtype=torch.int32, device=device)
    list_pos = torch.zeros(Pc, dtype=torch.int32, device=device)
    ws = []
    alphas, valids, parts = alpha.unbind(0), valid.unbind(0), part.unbind(0)
    for k in range(sub.shape[0]):
        gk = sub[k]
        a_k, v_k = alphas[k], valids[k] & ~done
        list_pos = list_pos + parts[k].to(torch.int32)
        test_T = T * (one - a_k)
        term = v_k & (test_T < t_min)  # stops BEFORE blending this splat
        blend = v_k & ~term
        done = done | term
        w = torch.where(blend, a_k * T, zero)
        Cacc = Cacc + w[None, :] * colors[gk][:, None]
        Dacc = Dacc + w * depths[gk]
        T = torch.where(blend, test_T, T)
        n_bl = n_bl + blend.to(torch.int32)
        n_co = torch.where(blend, list_pos, n_co)
        ws.append(w)
    W = torch.zeros(colors.shape[0], Pc, dtype=dtype, device=device)
    if ws:
        W = W.index_copy(0, sub, torch.stack(ws, dim=0))
    return Cacc, Dacc, T, n_bl, n_co, W


def _blend(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
    pixel_chunk: int | None,
):
    """Front-to-back blending of all pixels; returns per-pixel sums and per-Gaussian weights.

    Returns:
        (C [3, P], D [P], T [P], n_blended [P], n_contrib [P], weights [N, P]) with
        P = H * W in row-major pixel order.
    """
    P = width * height
    order, spans = _depth_order(means2d, conics, opacities, depths, radii, width, height)
    grid = _pixel_grid(width, height, means2d)
    chunk = P if pixel_chunk is None else max(1, int(pixel_chunk))
    outs = []
    for start in range(0, max(P, 1), chunk):
        pixels = tuple(v[start : min(P, start + chunk)] for v in grid)
        sub, part, alpha, valid = _chunk_alphas(order, spans, means2d, conics, opacities, pixels)
        outs.append(_composite(sub, part, alpha, valid, colors, depths))
    C, D, T, n_bl, n_co, W = zip(*outs)
    return (
        torch.cat(C, dim=1)[:, :P],
        torch.cat(D)[:P],
        torch.cat(T)[:P],
        torch.cat(n_bl)[:P],
        torch.cat(n_co)[:P],
        torch.cat(W, dim=1)[:, :P],
    )


def reference_rasterize_projected(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
    *,
    pixel_chunk: int | None = None,
) -> ReferenceRender:
    """Alpha-blend projected 2-D Gaussians (the semantics of the rasterization kernel).

    A Gaussian takes part at pixel (i, j) iff it is binned to the pixel's tile (i // TILE_SIZE,
    j // TILE_SIZE): ``radii > 0``, the tile lies in its rectangle (``tile_rect``) and holds a pixel
    centre its opacity-aware ellipse reaches (:func:`reference_tile_spans`). Splats are visited by ascending depth (ties: lower
    index first); a splat with power > 0 or alpha < ALPHA_MIN is skipped (no effect on T);
    a pixel stops before the first splat that would bring T below T_MIN.

    Args:
        means2d: [N, 2] projected centres (image frame, pixels).
        conics: [N, 3] inverse 2-D covariances (a, b, c).
        colors: [N, 3] RGB.
        opacities: [N] opacities in [0, 1].
        depths: [N] view-space depths (sort key and depth output).
        radii: [N] integer pixel radii, 0 = culled; not differentiated.
        width: image width W in pixels.
        height: image height H in pixels.
        background: [3] RGB background added as ``final_T * background``; None: black.
        pixel_chunk: process this many pixels at a time (bounds temporary memory).

    Returns:
        A :class:`ReferenceRender` with ``projection=None``.
    """
    dtype, device = means2d.dtype, means2d.device
    if background is None:
        background = torch.zeros(3, dtype=dtype, device=device)
    background = background.to(dtype=dtype, device=device)
    Cacc, Dacc, T, n_bl, n_co, W = _blend(
        means2d, conics, colors, opacities, depths, radii, width, height, pixel_chunk
    )
    H_, W_ = height, width
    image = (Cacc + T[None, :] * background[:, None]).reshape(3, H_, W_)
    return ReferenceRender(
        image=image,
        alpha=(1 - T).reshape(1, H_, W_),
        depth=Dacc.reshape(1, H_, W_),
        final_T=T.reshape(H_, W_),
        n_blended=n_bl.reshape(H_, W_),
        n_contrib=n_co.reshape(H_, W_),
        weights=W.reshape(-1, H_, W_),
        projection=None,
    )


def reference_rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    sh: torch.Tensor,
    viewmat: torch.Tensor,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    sh_degree: int,
    background: torch.Tensor | None = None,
    *,
    pixel_chunk: int | None = None,
) -> ReferenceRender:
    """Render 3-D Gaussians: :func:`reference_project` then :func:`reference_rasterize_projected`.

    Args:
        means: [N, 3] centres, world frame.
        quats: [N, 4] rotations (w, x, y, z), unnormalised.
        log_scales: [N, 3] log scales.
        opacity_logits: [N] opacity logits.
        sh: [N, K, 3] SH coefficients, or [N, 3] direct colours when ``sh_degree == -1``.
        viewmat: [4, 4] world-to-camera, OpenCV axes.
        fx: focal length x (pixels).
        fy: focal length y (pixels).
        cx: principal point x (pixels, image frame).
        cy: principal point y (pixels, image frame).
        width: image width W.
        height: image height H.
        sh_degree: active SH degree, or -1 for direct colours.
        background: [3] RGB background; None: black.
        pixel_chunk: see :func:`reference_rasterize_projected`.

    Returns:
        A :class:`ReferenceRender` (image [3, H, W], alpha [1, H, W], depth [1, H, W], final_T
        [H, W], n_blended / n_contrib [H, W] int32, weights [N, H, W]) with its projection.
    """
    proj = reference_project(
        means, quats, log_scales, opacity_logits, sh, viewmat, fx, fy, cx, cy, width, height,
        sh_degree,
    )
    out = reference_rasterize_projected(
        proj.means2d, proj.conics, proj.colors, proj.opacities, proj.depths, proj.radii,
        width, height, background, pixel_chunk=pixel_chunk,
    )
    return out._replace(projection=proj)


def reference_contribution(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
    weights: torch.Tensor,
    *,
    pixel_chunk: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-Gaussian contribution of the blending weights under a weight map.

    With ``w_i(p) = alpha_i(p) T_i(p)`` the blending weight of Gaussian i at pixel p (0 if not
    blended there): ``V[i, c] = sum_p weights[c, p] w_i(p)``, ``hits[i] = #{p : w_i(p) > 0}``,
    ``max_weight[i] = max_p w_i(p)`` (0 for a Gaussian that is never blended).

    Args:
        means2d: [N, 2] projected centres (image frame, pixels).
        conics: [N, 3] inverse 2-D covariances (a, b, c).
        opacities: [N] opacities.
        depths: [N] view-space depths (only the order matters here).
        radii: [N] integer pixel radii, 0 = culled.
        width: image width W.
        height: image height H.
        weights: [C, H, W] weight map.
        pixel_chunk: see :func:`reference_rasterize_projected`.

    Returns:
        (V [N, C], hits [N] int32, max_weight [N]); V and max_weight are differentiable.
    """
    N = means2d.shape[0]
    colors = torch.zeros(N, 3, dtype=means2d.dtype, device=means2d.device)
    _, _, _, _, _, W = _blend(
        means2d, conics, colors, opacities, depths, radii, width, height, pixel_chunk
    )
    Cn = weights.shape[0]
    wmap = weights.reshape(Cn, -1).to(W.dtype)
    V = W @ wmap.transpose(0, 1)  # [N, C]
    hits = (W > 0).sum(dim=-1).to(torch.int32)
    if W.shape[1] == 0:
        max_w = torch.zeros(N, dtype=W.dtype, device=W.device)
    else:
        max_w = W.max(dim=-1).values
    return V, hits, max_w
