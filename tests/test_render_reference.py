"""Tests of the pure-PyTorch reference rasterizer (gsw.render._reference)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gsw import constants as K
from gsw.render._reference import (
    reference_contribution,
    reference_project,
    reference_rasterize,
    reference_rasterize_projected,
    reference_sh_basis,
)

W = H = 32
FX = FY = 40.0
CX = CY = 16.5  # the camera axis hits the centre of pixel (16, 16)


def _identity_scene(zs, log_scale=-2.0, logit=0.5, colors=None, dtype=torch.float64):
    n = len(zs)
    means = torch.tensor([[0.0, 0.0, z] for z in zs], dtype=dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=dtype)
    log_scales = torch.full((n, 3), log_scale, dtype=dtype)
    logits = torch.full((n,), logit, dtype=dtype)
    if colors is None:
        colors = torch.tensor([[0.9, 0.4, 0.1]] * n, dtype=dtype)
    return means, quats, log_scales, logits, colors.to(dtype)


def _render(means, quats, log_scales, logits, sh, sh_degree=-1, bg=None, viewmat=None, **kw):
    dtype = means.dtype
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype) if bg is None else bg
    viewmat = torch.eye(4, dtype=dtype) if viewmat is None else viewmat
    return reference_rasterize(
        means, quats, log_scales, logits, sh, viewmat, FX, FY, CX, CY, W, H, sh_degree, bg, **kw
    )


def _sequential_T(alphas):
    """The termination rule written out naively: returns (final T, number blended)."""
    T, n = 1.0, 0
    for a in alphas:
        if a < K.ALPHA_MIN:
            continue
        if T * (1.0 - a) < K.T_MIN:
            break
        T *= 1.0 - a
        n += 1
    return T, n


# ------------------------------------------------------------------ projection / single splat


def test_single_isotropic_gaussian_analytic():
    z, ls, logit = 2.0, -2.0, 0.5
    means, quats, log_scales, logits, colors = _identity_scene([z], ls, logit)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out = _render(means, quats, log_scales, logits, colors, bg=bg)
    proj = out.projection
    op = 1.0 / (1.0 + math.exp(-logit))
    # EWA of an isotropic Gaussian on the optical axis: J = diag(f/z), so
    # cov2d = (f sigma / z)^2 + dilation.
    var = (FX * math.exp(ls) / z) ** 2 + K.COV2D_DILATION
    torch.testing.assert_close(proj.means2d[0], torch.tensor([CX, CY], dtype=torch.float64))
    torch.testing.assert_close(proj.conics[0], torch.tensor([1 / var, 0.0, 1 / var], dtype=torch.float64))
    assert int(proj.radii[0]) == math.ceil(K.RADIUS_SIGMAS * math.sqrt(var + math.sqrt(K.EIGEN_FLOOR)))
    assert float(proj.depths[0]) == z
    # Peak at the projected centre: power 0, alpha = opacity.
    i = j = int(CX - 0.5)
    expected = op * colors[0] + (1 - op) * bg
    torch.testing.assert_close(out.image[:, j, i], expected)
    assert float(out.alpha[0, j, i]) == pytest.approx(op)
    assert float(out.depth[0, j, i]) == pytest.approx(op * z)
    # One pixel to the right: dx = -1 -> alpha = op * exp(-0.5 / var).
    a1 = op * math.exp(-0.5 / var)
    torch.testing.assert_close(out.image[:, j, i + 1], a1 * colors[0] + (1 - a1) * bg)
    assert int(out.n_blended[j, i]) == 1 and int(out.n_contrib[j, i]) == 1


def test_sh_degree0_colour():
    means, quats, log_scales, logits, _ = _identity_scene([2.0])
    f_dc = torch.tensor([[[0.7, -0.3, -3.0]]], dtype=torch.float64)
    proj = reference_project(
        means, quats, log_scales, logits, f_dc, torch.eye(4, dtype=torch.float64),
        FX, FY, CX, CY, W, H, 0,
    )
    expected = (K.SH_C0 * f_dc[0, 0] + K.SH_COLOR_OFFSET).clamp_min(0)
    torch.testing.assert_close(proj.colors[0], expected)
    assert float(proj.colors[0, 2]) == 0.0  # clamped at 0


def test_sh_uses_only_active_coefficients():
    torch.manual_seed(0)
    means, quats, log_scales, logits, _ = _identity_scene([2.0, 3.0])
    means[:, 0] = torch.tensor([0.3, -0.2], dtype=torch.float64)
    sh = torch.randn(2, 16, 3, dtype=torch.float64) * 0.2
    vm = torch.eye(4, dtype=torch.float64)
    args = (means, quats, log_scales, logits)
    c1 = reference_project(*args, sh, vm, FX, FY, CX, CY, W, H, 1).colors
    c1b = reference_project(*args, sh[:, :4].clone(), vm, FX, FY, CX, CY, W, H, 1).colors
    torch.testing.assert_close(c1, c1b)
    # degree 1 by hand: dir = normalised(mean - camera centre) with camera centre 0
    d = means / means.norm(dim=-1, keepdim=True)
    b = reference_sh_basis(1, d)
    manual = K.SH_COLOR_OFFSET + sum(b[:, k : k + 1] * sh[:, k] for k in range(4))
    torch.testing.assert_close(c1, manual.clamp_min(0))


def _random_unit(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return d / d.norm(dim=-1, keepdim=True)


def test_sh_basis_parity_and_addition_theorem():
    d = _random_unit(64)
    basis = reference_sh_basis(K.MAX_SH_DEGREE, d)
    basis_neg = reference_sh_basis(K.MAX_SH_DEGREE, -d)
    for l in range(K.MAX_SH_DEGREE + 1):
        sl = slice(l * l, (l + 1) * (l + 1))
        torch.testing.assert_close(basis_neg[:, sl], (-1) ** l * basis[:, sl])
        # addition theorem: sum_m Y_lm(d)^2 = (2l + 1) / (4 pi) for every unit d
        s = (basis[:, sl] ** 2).sum(-1)
        torch.testing.assert_close(s, torch.full_like(s, (2 * l + 1) / (4 * math.pi)))
    # lower degrees are prefixes of higher ones
    for deg in range(K.MAX_SH_DEGREE):
        torch.testing.assert_close(reference_sh_basis(deg, d), basis[:, : (deg + 1) ** 2])


def test_sh_basis_orthonormal_by_quadrature():
    # Gauss-Legendre in cos(theta) x uniform phi integrates polynomials of degree <= 6 exactly.
    nodes, wts = np.polynomial.legendre.leggauss(8)
    n_phi = 16
    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    ct, ph = np.meshgrid(nodes, phi, indexing="ij")
    st = np.sqrt(1 - ct**2)
    d = torch.tensor(np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3))
    w = torch.tensor(np.repeat(wts, n_phi) * (2 * np.pi / n_phi))
    Y = reference_sh_basis(K.MAX_SH_DEGREE, d)
    gram = Y.T @ (w[:, None] * Y)
    torch.testing.assert_close(gram, torch.eye(Y.shape[1], dtype=torch.float64))


# ------------------------------------------------------------------ culling


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_near_plane_culling(dtype):
    zs = [K.NEAR_PLANE * 0.5, K.NEAR_PLANE, -1.0, 2.0]
    means, quats, log_scales, logits, colors = _identity_scene(zs, dtype=dtype)
    means[:3, 0] = 0.0
    out = _render(means, quats, log_scales, logits, colors)
    assert out.projection.radii.tolist()[:3] == [0, 0, 0]
    assert int(out.projection.radii[3]) > 0
    # only the visible one is rendered
    alone = _render(means[3:], quats[3:], log_scales[3:], logits[3:], colors[3:])
    torch.testing.assert_close(out.image, alone.image)
    # all culled -> background
    out0 = _render(means[:3], quats[:3], log_scales[:3], logits[:3], colors[:3])
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype)
    torch.testing.assert_close(out0.image, bg[:, None, None].expand(3, H, W))
    assert torch.all(out0.alpha == 0)


def test_empty_scene():
    e = torch.zeros(0, 3, dtype=torch.float64)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64, requires_grad=True)
    out = _render(e, torch.zeros(0, 4, dtype=torch.float64), e, torch.zeros(0, dtype=torch.float64), e, bg=bg)
    torch.testing.assert_close(out.image, bg.detach()[:, None, None].expand(3, H, W))
    assert out.weights.shape == (0, H, W) and torch.all(out.final_T == 1)
    out.image.sum().backward()
    torch.testing.assert_close(bg.grad, torch.full((3,), float(H * W), dtype=torch.float64))


def test_offscreen_gaussian_culled_by_zero_tiles():
    means, quats, log_scales, logits, colors = _identity_scene([2.0])
    means[0, 0] = 20.0  # far to the right, footprint entirely outside the image
    out = _render(means, quats, log_scales, logits, colors)
    assert int(out.projection.radii[0]) == 0
    assert torch.all(out.projection.tile_rects == 0)


def test_frustum_clamp_zero_gradient():
    # A Gaussian just off the right border (still touching the image): x/z beyond the clamp.
    means, quats, log_scales, logits, colors = _identity_scene([1.0], log_scale=0.5)
    lim_pos = (W - CX) / FX + (K.FRUSTUM_CLAMP - 1) * 0.5 * W / FX
    means[0, 0] = 1.05 * lim_pos
    means.requires_grad_(True)
    proj = reference_project(
        means, quats, log_scales, logits, colors, torch.eye(4, dtype=torch.float64),
        FX, FY, CX, CY, W, H, -1,
    )
    assert int(proj.radii[0]) > 0
    # conic depends on x only through the clamped ratio -> zero gradient w.r.t. x
    (g,) = torch.autograd.grad(proj.conics.sum(), means)
    assert g[0, 0] == 0 and g[0, 2] != 0
    # mean2d uses the unclamped ratio
    assert proj.means2d[0, 0].item() == pytest.approx(FX * means[0, 0].item() + CX)


# ------------------------------------------------------------------ blending rules


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n_stack", [3, 5])
def test_termination_rule(dtype, n_stack):
    cols = torch.eye(3, dtype=dtype).repeat(2, 1)[:n_stack]
    zs = [2.0 + k for k in range(n_stack)]
    # opaque: opacity > ALPHA_MAX, and large so that alpha is clamped at the centre
    means, quats, log_scales, logits, colors = _identity_scene(zs, 0.0, 10.0, cols, dtype)
    out = _render(means, quats, log_scales, logits, colors)
    assert torch.all(out.final_T >= K.T_MIN)
    j = i = int(CX - 0.5)
    a = torch.tensor(K.ALPHA_MAX, dtype=dtype)
    T_ref, n_ref = _sequential_T([a.item()] * n_stack)
    assert int(out.n_blended[j, i]) == n_ref
    if n_stack == 5:
        assert n_ref < n_stack  # the rule did stop this pixel
    assert float(out.final_T[j, i]) == pytest.approx(T_ref, rel=1e-5)
    # excluded splats contribute nothing: their weights are zero at that pixel
    assert torch.all(out.weights[n_ref:, j, i] == 0)
    w_expected, T = [], 1.0
    for _ in range(n_ref):
        w_expected.append(a.item() * T)
        T *= 1 - a.item()
    torch.testing.assert_close(
        out.weights[:n_ref, j, i], torch.tensor(w_expected, dtype=dtype), rtol=1e-5, atol=1e-7
    )


def test_depth_order_and_ties():
    # the same two Gaussians given in either order render the same image; equal depths are
    # broken by index.
    cols = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    means, quats, log_scales, logits, colors = _identity_scene([3.0, 2.0], -1.0, 1.0, cols)
    a = _render(means, quats, log_scales, logits, colors)
    p = [1, 0]
    b = _render(means[p], quats[p], log_scales[p], logits[p], colors[p])
    torch.testing.assert_close(a.image, b.image)
    j = i = int(CX - 0.5)
    assert a.weights[1, j, i] > a.weights[0, j, i]  # the nearer one (index 1) is in front
    means2 = means.clone()
    means2[:, 2] = 2.0  # tie: index 0 first
    c = _render(means2, quats, log_scales, logits, colors)
    assert c.weights[0, j, i] > c.weights[1, j, i]


def test_alpha_consistency_random_scene():
    torch.manual_seed(1)
    n = 40
    means = torch.randn(n, 3, dtype=torch.float64) * 0.6 + torch.tensor([0, 0, 3.0], dtype=torch.float64)
    quats = torch.randn(n, 4, dtype=torch.float64)
    log_scales = torch.randn(n, 3, dtype=torch.float64) * 0.3 - 2.0
    logits = torch.randn(n, dtype=torch.float64) * 2
    sh = torch.randn(n, 16, 3, dtype=torch.float64) * 0.3
    out = _render(means, quats, log_scales, logits, sh, sh_degree=3)
    torch.testing.assert_close(out.alpha[0], 1 - out.final_T)
    torch.testing.assert_close(out.weights.sum(0), out.alpha[0])  # telescoping sum of weights
    torch.testing.assert_close(out.depth[0], (out.weights * out.projection.depths[:, None, None]).sum(0))
    assert torch.all(out.final_T >= K.T_MIN) and torch.all(out.final_T <= 1)
    assert torch.all(out.n_contrib >= out.n_blended)
    # chunked evaluation is identical
    chunked = _render(means, quats, log_scales, logits, sh, sh_degree=3, pixel_chunk=100)
    for x, y in zip(out[:7], chunked[:7]):
        torch.testing.assert_close(x, y)
    # the 2-D stage alone gives the same image
    pr = out.projection
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    two_d = reference_rasterize_projected(
        pr.means2d, pr.conics, pr.colors, pr.opacities, pr.depths, pr.radii, W, H, bg
    )
    torch.testing.assert_close(two_d.image, out.image)
    # contribution
    wmap = torch.rand(2, H, W, dtype=torch.float64)
    V, hits, max_w = reference_contribution(
        pr.means2d, pr.conics, pr.opacities, pr.depths, pr.radii, W, H, wmap
    )
    torch.testing.assert_close(V, torch.einsum("nhw,chw->nc", out.weights, wmap))
    assert hits.dtype == torch.int32
    assert hits.tolist() == (out.weights > 0).flatten(1).sum(1).tolist()
    torch.testing.assert_close(max_w, out.weights.flatten(1).max(1).values)
    assert torch.all(hits[pr.radii == 0] == 0)


# ------------------------------------------------------------------ autograd


def test_gradcheck_tiny_scene():
    dtype = torch.float64
    means = torch.tensor([[0.05, -0.03, 2.0], [-0.1, 0.08, 2.6]], dtype=dtype)
    quats = torch.tensor([[0.9, 0.1, -0.2, 0.3], [0.7, -0.3, 0.2, 0.1]], dtype=dtype)
    log_scales = torch.tensor([[-2.6, -2.9, -2.7], [-2.5, -2.8, -3.0]], dtype=dtype)
    logits = torch.tensor([0.3, -0.2], dtype=dtype)
    g = torch.Generator().manual_seed(3)
    sh = torch.randn(2, 4, 3, generator=g, dtype=dtype) * 0.2
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype)
    vm = torch.eye(4, dtype=dtype)
    vm[:3, 3] = torch.tensor([0.01, -0.02, 0.05], dtype=dtype)
    n, f, c = 8, 10.0, 4.2

    def fn(m, q, s, o, shc, b):
        out = reference_rasterize(m, q, s, o, shc, vm, f, f * 1.1, c, c - 0.3, n, n, 1, b)
        return out.image, out.depth, out.alpha

    inputs = [x.clone().requires_grad_(True) for x in (means, quats, log_scales, logits, sh, bg)]
    out = fn(*inputs)
    assert (out[2] > K.ALPHA_MIN).any()
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradcheck_2d_stage_and_contribution():
    dtype = torch.float64
    means2d = torch.tensor([[3.7, 4.2], [4.6, 3.1]], dtype=dtype)
    conics = torch.tensor([[0.30, 0.05, 0.25], [0.20, -0.04, 0.35]], dtype=dtype)
    colors = torch.tensor([[0.9, 0.2, 0.4], [0.1, 0.7, 0.5]], dtype=dtype)
    opac = torch.tensor([0.8, 0.6], dtype=dtype)
    depths = torch.tensor([2.0, 1.5], dtype=dtype)
    radii = torch.tensor([5, 6], dtype=torch.int32)
    bg = torch.tensor([0.3, 0.3, 0.3], dtype=dtype)
    wmap = torch.rand(2, 8, 8, dtype=dtype, generator=torch.Generator().manual_seed(0))

    def fn(m, co, col, op, d, b):
        out = reference_rasterize_projected(m, co, col, op, d, radii, 8, 8, b)
        V, _, mw = reference_contribution(m, co, op, d, radii, 8, 8, wmap)
        return out.image, out.depth, V, mw

    inputs = [x.clone().requires_grad_(True) for x in (means2d, conics, colors, opac, depths, bg)]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradients_finite_with_culled_and_clamped():
    torch.manual_seed(2)
    n = 12
    means = torch.randn(n, 3) * 0.8 + torch.tensor([0, 0, 2.0])
    means[0, 2] = 0.0  # at the camera centre plane (culled; direction would be degenerate)
    means[1] = torch.tensor([0.0, 0.0, -0.5])
    means[2, 0] = 30.0  # off-screen
    params = [
        means,
        torch.randn(n, 4),
        torch.randn(n, 3) * 0.3 - 2.0,
        torch.randn(n) + 3.0,  # many clamped at ALPHA_MAX
        torch.randn(n, 9, 3) * 0.5,
    ]
    params = [p.clone().requires_grad_(True) for p in params]
    out = _render(*params, sh_degree=2, bg=torch.zeros(3), viewmat=torch.eye(4))
    (out.image.sum() + out.depth.sum() + out.alpha.sum()).backward()
    for p in params:
        assert p.grad is not None and torch.isfinite(p.grad).all()
    assert torch.all(params[0].grad[:3] == 0)  # culled Gaussians get no gradient
