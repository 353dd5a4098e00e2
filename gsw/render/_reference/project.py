"""Stage 1 of the reference rasterizer: 3-D Gaussians -> 2-D splats (the projection kernel's semantics).

See :mod:`gsw.render._reference` for the conventions (frames, masks, dtype, association order).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from gsw import constants as K

__all__ = ["ReferenceProjection", "reference_sh_basis", "reference_tile_rects", "reference_project"]


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


def _to_camera(means: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> list[torch.Tensor]:
    """``p_cam = R p + t`` with the summation order of ``matvec``: three [N] coordinates (x, y, z)."""
    x, y, z = means[:, 0], means[:, 1], means[:, 2]
    return [((R[i, 0] * x + R[i, 1] * y) + R[i, 2] * z) + t[i] for i in range(3)]


def _camera_covariance(quats: torch.Tensor, log_scales: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """3-D covariance in the camera frame, ``R (R_q S S R_q^T) R^T``: [N, 3, 3]."""
    Rq = _quat_to_rotmat(quats)
    M = Rq * torch.exp(log_scales)[:, None, :]
    sigma = _mm(M, M.transpose(-1, -2))
    Rb = R.expand(quats.shape[0], 3, 3)
    return _mm(_mm(Rb, sigma), Rb.transpose(-1, -2))


def _frustum_limits(focal: torch.Tensor, principal: torch.Tensor, size: int,
                    like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``frustum_limits``: the (negative, positive) bounds of the view ratio along one axis."""
    one = _c(1.0, like)
    tan_half = _c(0.5, like) * _c(float(size), like) / focal
    margin = (_c(K.FRUSTUM_CLAMP, like) - one) * tan_half
    return principal / focal + margin, (_c(float(size), like) - principal) / focal + margin


def _clamp_ratio(r: torch.Tensor, lneg: torch.Tensor, lpos: torch.Tensor) -> torch.Tensor:
    """``clamp_ratio``: r < -lneg ? -lneg : (r > lpos ? lpos : r); zero gradient through a clamped ratio."""
    return torch.where(r < -lneg, -lneg, torch.where(r > lpos, lpos, r))


def _ewa_cov2d(cov: torch.Tensor, pcx: torch.Tensor, pcy: torch.Tensor, iz: torch.Tensor,
               intrinsics: tuple[torch.Tensor, ...], width: int, height: int) -> tuple[torch.Tensor, ...]:
    """EWA projection ``J cov J^T`` with the frustum-clamped ratios: the 2-D covariance (a, b, c), each [N].

    Args:
        cov: [N, 3, 3] camera-frame covariance.
        pcx: [N] camera-frame x.
        pcy: [N] camera-frame y.
        iz: [N] ``1 / z`` (safe for culled Gaussians).
        intrinsics: (fx, fy, cx, cy) in the working dtype.
        width: image width in pixels.
        height: image height in pixels.
    """
    fx, fy, cx, cy = intrinsics
    lxn, lxp = _frustum_limits(fx, cx, width, cov)
    lyn, lyp = _frustum_limits(fy, cy, height, cov)
    u, v = _clamp_ratio(pcx * iz, lxn, lxp), _clamp_ratio(pcy * iz, lyn, lyp)
    j00, j02 = fx * iz, -fx * u * iz
    j11, j12 = fy * iz, -fy * v * iz
    r0 = [j00 * cov[:, 0, k] + j02 * cov[:, 2, k] for k in range(3)]
    r1 = [j11 * cov[:, 1, k] + j12 * cov[:, 2, k] for k in range(3)]
    return r0[0] * j00 + r0[2] * j02, r0[1] * j11 + r0[2] * j12, r1[1] * j11 + r1[2] * j12


@torch.no_grad()
def _footprint(a_d: torch.Tensor, c_d: torch.Tensor, det: torch.Tensor, ok: torch.Tensor,
               means2d: torch.Tensor, width: int, height: int, opacity_logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``footprint_radius`` and the tile rectangle (discrete, not differentiated).

    Args:
        a_d: [N] dilated 2-D covariance entry a.
        c_d: [N] dilated 2-D covariance entry c.
        det: [N] determinant of the dilated 2-D covariance.
        ok: [N] bool, in front of the near plane with a positive determinant.
        means2d: [N, 2] projected centres (zero where not ``ok``).
        width: image width in pixels.
        height: image height in pixels.
        opacity_logits: [N] opacity logits (the radius is opacity-aware).

    Returns:
        (radius [N] int32, tile_rects [N, 4] int32, ok [N]): ``ok`` also requires a non-empty rectangle;
        radius and rectangle are zero where it fails.
    """
    mid = _c(0.5, a_d) * (a_d + c_d)
    disc = mid * mid - det
    floor_ = _c(K.EIGEN_FLOOR, a_d)
    sigma = torch.sqrt(mid + torch.sqrt(torch.where(disc > floor_, disc, floor_)))
    # Opacity-aware (footprint_radius): min(ceil(3 sigma), ceil(e sigma) + 1), e the extent in sigmas
    # where alpha can reach ALPHA_MIN; 0 where it never can.
    zero, one = _c(0.0, a_d), _c(1.0, a_d)
    skip = torch.log(_c(K.ALPHA_MIN, a_d) / torch.sigmoid(opacity_logits.to(a_d))) - _c(K.SKIP_LOG_MARGIN, a_d)
    extent = torch.sqrt(torch.where(skip < 0, _c(-2.0, a_d) * skip, zero))
    radius = torch.minimum(torch.ceil(_c(K.RADIUS_SIGMAS, a_d) * sigma), torch.ceil(extent * sigma) + one)
    radius = torch.where(extent > 0, radius, zero)
    radius = torch.where(ok, radius, torch.zeros_like(radius)).to(torch.int32)
    rects = reference_tile_rects(means2d, radius, width, height)
    n_tiles = (rects[:, 2] - rects[:, 0]) * (rects[:, 3] - rects[:, 1])
    ok = ok & (n_tiles > 0)
    radius = torch.where(ok, radius, torch.zeros_like(radius))
    rects = torch.where(ok[:, None], rects, torch.zeros_like(rects))
    return radius, rects, ok


def _colors(means: torch.Tensor, sh: torch.Tensor, sh_degree: int, R: torch.Tensor,
            t: torch.Tensor) -> torch.Tensor:
    """RGB [N, 3]: the direct colours (``sh_degree == -1``), else SH evaluated towards the camera, clamped at 0."""
    if sh_degree < 0:
        if sh.dim() != 2 or sh.shape[-1] != 3:
            raise ValueError("sh_degree == -1 expects direct colours of shape [N, 3]")
        return sh
    n_coeffs = (sh_degree + 1) ** 2
    if sh.dim() != 3 or sh.shape[1] < n_coeffs or sh.shape[2] != 3:
        raise ValueError(f"sh must be [N, >= {n_coeffs}, 3] for degree {sh_degree}")
    if sh_degree == 0:
        dirs = torch.zeros_like(means)  # the degree-0 basis ignores the direction
    else:
        one = _c(1.0, means)
        cam_c = [-(R[0, i] * t[0] + R[1, i] * t[1] + R[2, i] * t[2]) for i in range(3)]
        d = [means[:, i] - cam_c[i] for i in range(3)]
        sq = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        dinv = one / torch.sqrt(torch.where(sq > 0, sq, one))
        dirs = torch.stack([d[0] * dinv, d[1] * dinv, d[2] * dinv], dim=-1)
    basis = reference_sh_basis(sh_degree, dirs)
    rgb = torch.full_like(means, K.SH_COLOR_OFFSET)
    for k in range(n_coeffs):
        rgb = rgb + basis[:, k : k + 1] * sh[:, k, :]
    return torch.where(rgb > 0, rgb, torch.zeros_like(rgb))


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
    if sh_degree > K.MAX_SH_DEGREE or sh_degree < -1:
        raise ValueError(f"sh_degree {sh_degree} outside [-1, {K.MAX_SH_DEGREE}]")
    vm = viewmat.to(dtype=dtype, device=device)
    R, t = vm[:3, :3], vm[:3, 3]
    zero = torch.zeros((), dtype=dtype, device=device)
    one = _c(1.0, means)
    # Camera parameters in the working dtype (Camera<T> stores T fx, ...).
    fx_t, fy_t, cx_t, cy_t = (_c(float(v), means) for v in (fx, fy, cx, cy))

    pcx, pcy, pcz = _to_camera(means, R, t)
    in_front = pcz > _c(K.NEAR_PLANE, means)
    iz = one / torch.where(in_front, pcz, one)
    cov_a, cov_b, cov_c = _ewa_cov2d(_camera_covariance(quats, log_scales, R), pcx, pcy, iz,
                                     (fx_t, fy_t, cx_t, cy_t), width, height)
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
    means2d_det = torch.stack([torch.where(ok, m2x, zero), torch.where(ok, m2y, zero)], -1).detach()
    radius, rects, ok = _footprint(a_d.detach(), c_d.detach(), det.detach(), ok, means2d_det, width, height,
                                   opacity_logits.detach())

    colors = _colors(means, sh, sh_degree, R, t)
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
