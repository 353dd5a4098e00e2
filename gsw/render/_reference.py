"""Dense, slow, pure-PyTorch reference rasterizer (differentiable by autograd).

This module re-implements, operation by operation, the semantics of the C++ kernels whose math
lives in ``csrc/core/math.h`` (thresholds in ``csrc/core/constants.h``, data layout in
``csrc/core/params.h``). It exists to test those kernels: forward outputs should agree to
about 1e-5 in float32 and gradients obtained by ``torch.autograd`` through this module are the
ground truth for the hand-written backward passes.

Design choices:
  * No tiling, sorting by tile or early-out tricks: every (Gaussian, pixel) pair is evaluated
    densely and the discrete rules (culling, tile membership, alpha thresholds, termination)
    are applied as boolean masks. Masks are computed from values and are never differentiated;
    the differentiable values go through ``torch.where`` so masked branches get exactly zero
    gradient, and every masked branch is fed "safe" inputs so that no NaN/inf can leak into the
    gradient.
  * Transmittance is propagated by an explicit front-to-back loop over the depth-sorted
    Gaussians, each step vectorised over all pixels. This reproduces the C++ sequence of
    float operations ``T <- T * (1 - alpha)`` exactly (``torch.cumprod`` accumulates float32 in
    double on CPU and would make the termination test disagree at the boundary).
  * Every threshold is imported from :mod:`gsw.constants` and cast to the working dtype
    first, like ``T(CONSTANT)`` in the C++ templates. Floating-point expressions are written
    in the same association order as ``math.h``.
  * Work is done in the dtype of ``means`` (float32 or float64). Memory is O(N * P) for N
    Gaussians and P pixels (kept for autograd anyway); ``pixel_chunk`` bounds the size of the
    temporary [N, P] tensors of one chunk.

Frames:
  * world: the frame of ``means``;
  * camera: ``p_cam = R p + t`` with ``viewmat = [[R, t], [0, 1]]`` world-to-camera, OpenCV
    axes (x right, y down, z forward);
  * image: ``mean2d = (fx x/z + cx, fy y/z + cy)`` in pixels; pixel (i, j) (column i, row j)
    has its centre at (i + 0.5, j + 0.5) in this frame.

Example:
    >>> import torch
    >>> from gsw.reference import reference_rasterize
    >>> out = reference_rasterize(
    ...     torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
    ...     torch.full((1, 3), -2.0), torch.zeros(1), torch.ones(1, 3), torch.eye(4),
    ...     20.0, 20.0, 8.5, 8.5, 16, 16, -1, torch.zeros(3))
    >>> out.image.shape
    torch.Size([3, 16, 16])
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from gsw import constants as K

__all__ = [
    "ReferenceProjection",
    "ReferenceRender",
    "reference_sh_basis",
    "reference_tile_rects",
    "reference_project",
    "reference_rasterize_projected",
    "reference_rasterize",
    "reference_contribution",
]


class ReferenceProjection(NamedTuple):
    """Per-Gaussian output of the projection stage (``ProjectParams`` outputs).

    Culled Gaussians (``radii == 0``) have all floating-point outputs set to zero (INRIA /
    gsplat convention: the kernel returns before writing them) and a zero tile rectangle.

    Attributes:
        means2d: [N, 2] projected centres in pixels (image frame, ``K p_cam``).
        conics: [N, 3] inverse of the dilated 2-D covariance, stored (a, b, c) =
            [[a, b], [b, c]].
        depths: [N] view-space depth z (camera frame).
        colors: [N, 3] RGB (from SH, or the direct colours when ``sh_degree == -1``).
        opacities: [N] ``sigmoid(opacity_logits)``.
        radii: [N] int32 pixel radius, 0 = culled.
        tile_rects: [N, 4] int32 tile rectangle (x0, y0, x1, y1), half-open [x0, x1) x [y0, y1)
            in tile units.
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    colors: torch.Tensor
    opacities: torch.Tensor
    radii: torch.Tensor
    tile_rects: torch.Tensor


class ReferenceRender(NamedTuple):
    """Output of the blending stage (``RasterParams`` outputs plus reference extras).

    Attributes:
        image: [3, H, W] ``sum_i w_i color_i + final_T * background``.
        alpha: [1, H, W] ``1 - final_T``.
        depth: [1, H, W] ``sum_i w_i z_i`` (not normalised by alpha).
        final_T: [H, W] transmittance left after the last blended splat.
        n_blended: [H, W] int32 number of splats blended into each pixel.
        n_contrib: [H, W] int32 ``1 + index`` of the last blended splat in the pixel's tile
            list (the depth-sorted list of Gaussians whose tile rectangle contains the pixel's
            tile), 0 if none; same meaning as ``RasterParams::n_contrib``.
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


# ------------------------------------------------------------------ helpers


def _c(value: float, like: torch.Tensor) -> torch.Tensor:
    """A 0-dim tensor holding ``value`` in ``like``'s dtype/device (``T(value)`` in C++)."""
    return torch.tensor(value, dtype=like.dtype, device=like.device)


def _mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Batched 3x3 product with the summation order of ``gsw::matmul``: [..., 3, 3]."""
    return (a[..., :, 0:1] * b[..., 0:1, :] + a[..., :, 1:2] * b[..., 1:2, :]) + a[
        ..., :, 2:3
    ] * b[..., 2:3, :]


def _quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix [N, 3, 3] of the normalised quaternions q [N, 4] (w, x, y, z)."""
    inv = 1.0 / torch.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3])
    w, x, y, z = q[:, 0] * inv, q[:, 1] * inv, q[:, 2] * inv, q[:, 3] * inv
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def reference_sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Real SH basis exactly as ``gsw::sh_basis`` (INRIA ordering and signs).

    Args:
        degree: SH degree in [0, MAX_SH_DEGREE].
        dirs: [N, 3] unit directions (world frame).

    Returns:
        [N, (degree + 1)^2] basis values.
    """
    if not 0 <= degree <= K.MAX_SH_DEGREE:
        raise ValueError(f"sh degree {degree} outside [0, {K.MAX_SH_DEGREE}]")
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = [torch.full_like(x, K.SH_C0)]
    if degree >= 1:
        c1 = _c(K.SH_C1, x)
        out += [-c1 * y, c1 * z, -c1 * x]
    if degree >= 2:
        c2 = [_c(v, x) for v in K.SH_C2]
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            c2[0] * xy,
            c2[1] * yz,
            c2[2] * (2 * zz - xx - yy),
            c2[3] * xz,
            c2[4] * (xx - yy),
        ]
    if degree >= 3:
        c3 = [_c(v, x) for v in K.SH_C3]
        out += [
            c3[0] * y * (3 * xx - yy),
            c3[1] * xy * z,
            c3[2] * y * (4 * zz - xx - yy),
            c3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            c3[4] * x * (4 * zz - xx - yy),
            c3[5] * z * (xx - yy),
            c3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def _num_tiles(width: int, height: int) -> tuple[int, int]:
    return (width + K.TILE_SIZE - 1) // K.TILE_SIZE, (height + K.TILE_SIZE - 1) // K.TILE_SIZE


def reference_tile_rects(
    means2d: torch.Tensor, radii: torch.Tensor, width: int, height: int
) -> torch.Tensor:
    """Tile rectangles exactly as ``gsw::tile_rect`` (INRIA getRect in pixel-centre coords).

    Args:
        means2d: [N, 2] projected centres (image frame, pixels); not differentiated.
        radii: [N] integer pixel radii; rectangles of radius-0 Gaussians are zeroed.
        width: image width in pixels.
        height: image height in pixels.

    Returns:
        [N, 4] int32 (x0, y0, x1, y1), half-open, in tiles, clamped to [0, tiles_x/y].
    """
    tiles_x, tiles_y = _num_tiles(width, height)
    m = means2d.detach()
    r = radii.to(m.dtype)
    ts = _c(float(K.TILE_SIZE), m)
    half, one = _c(0.5, m), _c(1.0, m)
    px, py = m[:, 0] - half, m[:, 1] - half

    def clampi(v: torch.Tensor, hi: int) -> torch.Tensor:
        return torch.clamp(torch.floor(v), 0, hi).to(torch.int32)

    x0 = clampi((px - r) / ts, tiles_x)
    x1 = clampi((px + r + ts - one) / ts, tiles_x)
    y0 = clampi((py - r) / ts, tiles_y)
    y1 = clampi((py + r + ts - one) / ts, tiles_y)
    rect = torch.stack([x0, y0, x1, y1], dim=-1)
    return torch.where((radii > 0)[:, None], rect, torch.zeros_like(rect))


# ------------------------------------------------------------------ stage 1: projection


def reference_project(
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
) -> ReferenceProjection:
    """Project 3-D Gaussians to the image (the semantics of the projection kernel).

    Args:
        means: [N, 3] centres, world frame.
        quats: [N, 4] rotations (w, x, y, z), unnormalised.
        log_scales: [N, 3] log standard deviations along the rotated axes.
        opacity_logits: [N] opacity logits.
        sh: [N, K, 3] SH coefficients (K >= (sh_degree + 1)^2, channel last) when
            ``sh_degree >= 0``; [N, 3] direct RGB colours (used as is, no clamp) when
            ``sh_degree == -1``.
        viewmat: [4, 4] world-to-camera matrix, OpenCV axes.
        fx: focal length in pixels along x.
        fy: focal length in pixels along y.
        cx: principal point x in pixels (image frame).
        cy: principal point y in pixels (image frame).
        width: image width in pixels.
        height: image height in pixels.
        sh_degree: active SH degree in [0, MAX_SH_DEGREE], or -1 for direct colours.

    Returns:
        A :class:`ReferenceProjection`; differentiable w.r.t. every floating input.
    """
    dtype, device = means.dtype, means.device
    N = means.shape[0]
    if sh_degree > K.MAX_SH_DEGREE or sh_degree < -1:
        raise ValueError(f"sh_degree {sh_degree} outside [-1, {K.MAX_SH_DEGREE}]")
    vm = viewmat.to(dtype=dtype, device=device)
    R, t = vm[:3, :3], vm[:3, 3]
    zero = torch.zeros((), dtype=dtype, device=device)
    one = _c(1.0, means)

    # Camera parameters in the working dtype (Camera<T> stores T fx, ...).
    fx_t, fy_t, cx_t, cy_t = (_c(float(v), means) for v in (fx, fy, cx, cy))

    # p_cam = R p + t, same summation order as matvec.
    x, y, z = means[:, 0], means[:, 1], means[:, 2]
    p_cam = [((R[i, 0] * x + R[i, 1] * y) + R[i, 2] * z) + t[i] for i in range(3)]
    pcx, pcy, pcz = p_cam
    in_front = pcz > _c(K.NEAR_PLANE, means)
    z_safe = torch.where(in_front, pcz, one)

    # Sigma = R_q S S R_q^T ; cov_cam = R Sigma R^T.
    Rq = _quat_to_rotmat(quats)
    M = Rq * torch.exp(log_scales)[:, None, :]
    sigma = _mm(M, M.transpose(-1, -2))
    Rb = R.expand(N, 3, 3)
    cov = _mm(_mm(Rb, sigma), Rb.transpose(-1, -2))

    # EWA projection with the frustum-clamped ratios (frustum_limits / clamp_ratio).
    def limits(focal: torch.Tensor, principal: torch.Tensor, size: int):
        tan_half = _c(0.5, means) * _c(float(size), means) / focal
        margin = (_c(K.FRUSTUM_CLAMP, means) - one) * tan_half
        return principal / focal + margin, (_c(float(size), means) - principal) / focal + margin

    lxn, lxp = limits(fx_t, cx_t, width)
    lyn, lyp = limits(fy_t, cy_t, height)
    iz = one / z_safe
    rx, ry = pcx * iz, pcy * iz

    def clamp_ratio(r: torch.Tensor, lneg: torch.Tensor, lpos: torch.Tensor) -> torch.Tensor:
        # r < -lneg ? -lneg : (r > lpos ? lpos : r); zero gradient through a clamped ratio.
        return torch.where(r < -lneg, -lneg, torch.where(r > lpos, lpos, r))

    u, v = clamp_ratio(rx, lxn, lxp), clamp_ratio(ry, lyn, lyp)
    j00, j02 = fx_t * iz, -fx_t * u * iz
    j11, j12 = fy_t * iz, -fy_t * v * iz
    c = cov
    r0 = [j00 * c[:, 0, k] + j02 * c[:, 2, k] for k in range(3)]
    r1 = [j11 * c[:, 1, k] + j12 * c[:, 2, k] for k in range(3)]
    cov_a = r0[0] * j00 + r0[2] * j02
    cov_b = r0[1] * j11 + r0[2] * j12
    cov_c = r1[1] * j11 + r1[2] * j12
    # mean2d uses the unclamped ratios.
    m2x = fx_t * pcx * iz + cx_t
    m2y = fy_t * pcy * iz + cy_t

    # conic_from_cov2d.
    dil = _c(K.COV2D_DILATION, means)
    a_d, c_d = cov_a + dil, cov_c + dil
    det = a_d * c_d - cov_b * cov_b
    ok = in_front & (det > 0)
    inv = one / torch.where(ok, det, one)
    conic = torch.stack([c_d * inv, -cov_b * inv, a_d * inv], dim=-1)

    # footprint_radius (discrete, not differentiated).
    with torch.no_grad():
        mid = _c(0.5, means) * (a_d + c_d)
        disc = mid * mid - det
        floor_ = _c(K.EIGEN_FLOOR, means)
        sigma = torch.sqrt(mid + torch.sqrt(torch.where(disc > floor_, disc, floor_)))
        # Opacity-aware (footprint_radius): min(ceil(3 sigma), ceil(e sigma) + 1), e the extent in sigmas
        # where alpha can reach ALPHA_MIN; 0 where it never can.
        skip = torch.log(_c(K.ALPHA_MIN, means) / torch.sigmoid(opacity_logits)) - _c(K.SKIP_LOG_MARGIN, means)
        extent = torch.sqrt(torch.where(skip < 0, _c(-2.0, means) * skip, zero))
        radius = torch.minimum(torch.ceil(_c(K.RADIUS_SIGMAS, means) * sigma), torch.ceil(extent * sigma) + one)
        radius = torch.where(extent > 0, radius, zero)
        radius = torch.where(ok, radius, torch.zeros_like(radius)).to(torch.int32)
        means2d_det = torch.stack([torch.where(ok, m2x, zero), torch.where(ok, m2y, zero)], -1)
        rects = reference_tile_rects(means2d_det, radius, width, height)
        n_tiles = (rects[:, 2] - rects[:, 0]) * (rects[:, 3] - rects[:, 1])
        ok = ok & (n_tiles > 0)
        radius = torch.where(ok, radius, torch.zeros_like(radius))
        rects = torch.where(ok[:, None], rects, torch.zeros_like(rects))

    # Colour.
    if sh_degree < 0:
        if sh.dim() != 2 or sh.shape[-1] != 3:
            raise ValueError("sh_degree == -1 expects direct colours of shape [N, 3]")
        colors = sh
    else:
        n_coeffs = (sh_degree + 1) ** 2
        if sh.dim() != 3 or sh.shape[1] < n_coeffs or sh.shape[2] != 3:
            raise ValueError(f"sh must be [N, >= {n_coeffs}, 3] for degree {sh_degree}")
        if sh_degree == 0:
            dirs = torch.zeros_like(means)  # the degree-0 basis ignores the direction
        else:
            cam_c = [-(R[0, i] * t[0] + R[1, i] * t[1] + R[2, i] * t[2]) for i in range(3)]
            d = [means[:, i] - cam_c[i] for i in range(3)]
            sq = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
            dinv = one / torch.sqrt(torch.where(sq > 0, sq, one))
            dirs = torch.stack([d[0] * dinv, d[1] * dinv, d[2] * dinv], dim=-1)
        basis = reference_sh_basis(sh_degree, dirs)
        rgb = torch.full_like(means, K.SH_COLOR_OFFSET)
        for k in range(n_coeffs):
            rgb = rgb + basis[:, k : k + 1] * sh[:, k, :]
        colors = torch.where(rgb > 0, rgb, torch.zeros_like(rgb))

    opac = torch.sigmoid(opacity_logits)
    okc = ok[:, None]
    return ReferenceProjection(
        means2d=torch.where(okc, torch.stack([m2x, m2y], dim=-1), zero),
        conics=torch.where(okc, conic, zero),
        depths=torch.where(ok, pcz, zero),
        colors=torch.where(okc, colors, zero),
        opacities=torch.where(ok, opac, zero),
        radii=radius,
        tile_rects=rects,
    )


# ------------------------------------------------------------------ stage 2: blending


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
    dtype, device = means2d.dtype, means2d.device
    N, P = means2d.shape[0], width * height
    rects = reference_tile_rects(means2d, radii, width, height)
    active = (radii > 0) & ((rects[:, 2] - rects[:, 0]) * (rects[:, 3] - rects[:, 1]) > 0)
    idx = torch.nonzero(active).flatten()
    # ascending depth, ties by Gaussian index (stable sort of an index-ordered subset)
    order = idx[torch.sort(depths.detach()[idx], stable=True).indices]

    jj, ii = torch.meshgrid(
        torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij"
    )
    ii, jj = ii.flatten(), jj.flatten()
    half = _c(0.5, means2d)
    px_all, py_all = ii.to(dtype) + half, jj.to(dtype) + half
    tx_all, ty_all = ii // K.TILE_SIZE, jj // K.TILE_SIZE
    alpha_max, alpha_min, t_min = (_c(v, means2d) for v in (K.ALPHA_MAX, K.ALPHA_MIN, K.T_MIN))
    zero, one = torch.zeros((), dtype=dtype, device=device), _c(1.0, means2d)

    chunk = P if pixel_chunk is None else max(1, int(pixel_chunk))
    outs_C, outs_D, outs_T, outs_nb, outs_nc, outs_w = [], [], [], [], [], []
    for start in range(0, max(P, 1), chunk):
        sl = slice(start, min(P, start + chunk))
        px, py, tx, ty = px_all[sl], py_all[sl], tx_all[sl], ty_all[sl]
        Pc = px.shape[0]
        r = rects[order]
        part = (
            (r[:, 0:1] <= tx) & (tx < r[:, 2:3]) & (r[:, 1:2] <= ty) & (ty < r[:, 3:4])
        )  # [n, Pc], Gaussians in depth order
        keep = part.any(dim=1)
        sub, part = order[keep], part[keep]
        m2, con, op = means2d[sub], conics[sub], opacities[sub]
        dx = m2[:, 0:1] - px
        dy = m2[:, 1:2] - py
        a, b, c = con[:, 0:1], con[:, 1:2], con[:, 2:3]
        power = -half * (a * dx * dx + c * dy * dy) - b * dx * dy
        pos = power > 0
        g = torch.exp(torch.where(pos, zero, power))
        a_raw = op[:, None] * g
        alpha = torch.where(a_raw < alpha_max, a_raw, alpha_max)
        valid = part & ~pos & (alpha >= alpha_min)
        alpha = torch.where(valid, alpha, zero)

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
        Wc = torch.zeros(N, Pc, dtype=dtype, device=device)
        if ws:
            Wc = Wc.index_copy(0, sub, torch.stack(ws, dim=0))
        outs_C.append(Cacc)
        outs_D.append(Dacc)
        outs_T.append(T)
        outs_nb.append(n_bl)
        outs_nc.append(n_co)
        outs_w.append(Wc)
    return (
        torch.cat(outs_C, dim=1)[:, :P],
        torch.cat(outs_D)[:P],
        torch.cat(outs_T)[:P],
        torch.cat(outs_nb)[:P],
        torch.cat(outs_nc)[:P],
        torch.cat(outs_w, dim=1)[:, :P],
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

    A Gaussian takes part at pixel (i, j) iff ``radii > 0``, its tile rectangle (recomputed
    from ``means2d`` and ``radii`` as ``tile_rect``) is non-empty and contains the pixel's tile
    (i // TILE_SIZE, j // TILE_SIZE). Splats are visited by ascending depth (ties: lower
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

