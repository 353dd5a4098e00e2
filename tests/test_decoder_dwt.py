"""bior4.4 / periodization DWT: filters, an independent matrix reference, perfect reconstruction."""

import numpy as np
import pytest
import torch

from gsw.decoder.dwt import bior44_filters, dwt2, idwt2, ll_subband, pad_to_multiple

# Published bior4.4 (CDF 9/7) filters as PyWavelets stores them (10 taps, leading/trailing zeros).
DEC_LO = [0.0, 0.03782845550726404, -0.023849465019556843, -0.11062440441843718, 0.37740285561283066,
          0.8526986790088938, 0.37740285561283066, -0.11062440441843718, -0.023849465019556843,
          0.03782845550726404]
DEC_HI = [0.0, -0.06453888262869706, 0.04068941760916406, 0.41809227322161724, -0.7884856164055829,
          0.41809227322161724, 0.04068941760916406, -0.06453888262869706, 0.0, 0.0]
REC_LO = [0.0, -0.06453888262869706, -0.04068941760916406, 0.41809227322161724, 0.7884856164055829,
          0.41809227322161724, -0.04068941760916406, -0.06453888262869706, 0.0, 0.0]


def test_filters_match_published_values():
    f = bior44_filters()
    np.testing.assert_allclose(f["h"], DEC_LO[1:], atol=1e-12)
    np.testing.assert_allclose(f["h1"], DEC_HI[1:8], atol=1e-12)
    np.testing.assert_allclose(f["g"], REC_LO[1:8], atol=1e-12)


def test_biorthogonality_and_vanishing_moments():
    f = bior44_filters()
    h, g = f["h"], np.concatenate([[0.0], f["g"], [0.0]])  # both on offsets -4..4
    for k in range(-3, 4):  # sum_n h[n] g[n - 2k] = delta_k
        s = sum(h[n + 4] * g[n - 2 * k + 4] for n in range(-4, 5) if -4 <= n - 2 * k <= 4)
        assert s == pytest.approx(1.0 if k == 0 else 0.0, abs=1e-12)
    m7, m9 = np.arange(-3, 4), np.arange(-4, 5)
    for p in range(4):  # 4 vanishing moments on both high-pass filters
        assert abs((m7**p * f["h1"]).sum()) < 1e-12
        assert abs((m9**p * f["g1"]).sum()) < 1e-12


def _matrix(filt10, n):
    """PyWavelets periodization analysis as a matrix: c[o] = sum_j f[j] x[(2o + 5 - j) mod n]."""
    a = np.zeros((n // 2, n))
    for o in range(n // 2):
        for j, v in enumerate(filt10):
            a[o, (2 * o + 5 - j) % n] += v
    return a


def _reference_dwt2(x, levels):
    ll, highs = x, []
    for _ in range(levels):
        h, w = ll.shape
        lo_h, hi_h = _matrix(DEC_LO, h), _matrix(DEC_HI, h)
        lo_w, hi_w = _matrix(DEC_LO, w), _matrix(DEC_HI, w)
        highs.append((hi_h @ ll @ lo_w.T, lo_h @ ll @ hi_w.T, hi_h @ ll @ hi_w.T))  # LH, HL, HH
        ll = lo_h @ ll @ lo_w.T
    return ll, highs


@pytest.mark.parametrize("shape", [(16, 24), (32, 8), (12, 20)])
def test_dwt2_matches_matrix_reference(shape):
    rng = np.random.default_rng(0)
    x = rng.standard_normal(shape)
    levels = 2
    ll, highs = dwt2(torch.from_numpy(x)[None, None], levels)
    ref_ll, ref_highs = _reference_dwt2(x, levels)
    np.testing.assert_allclose(ll[0, 0].numpy(), ref_ll, atol=1e-12)
    for got, ref in zip(highs, ref_highs):
        for g_, r_ in zip(got, ref):
            np.testing.assert_allclose(g_[0, 0].numpy(), r_, atol=1e-12)


@pytest.mark.parametrize("levels", [1, 2, 3])
def test_perfect_reconstruction(levels):
    x = torch.randn(2, 3, 40, 24, dtype=torch.float64)
    ll, highs = dwt2(x, levels)
    assert torch.allclose(idwt2(ll, highs), x, atol=1e-12)
    x32 = x.float()
    assert torch.allclose(idwt2(*dwt2(x32, levels)), x32, atol=1e-5)


def test_sizes_not_divisible_are_reflect_padded():
    x = torch.randn(1, 3, 37, 50, dtype=torch.float64)
    ll, highs = dwt2(x, 2)
    assert ll.shape[-2:] == (10, 13)  # padded to 40 x 52
    padded = torch.nn.functional.pad(x, (0, 2, 0, 3), mode="reflect")
    assert torch.equal(pad_to_multiple(x, 4), padded)
    assert torch.allclose(idwt2(ll, highs, size=(37, 50)), x, atol=1e-12)
    tiny = torch.randn(1, 1, 2, 3)  # too small to reflect: replicate
    assert dwt2(tiny, 2)[0].shape[-2:] == (1, 1)


def test_constant_image_and_dtype():
    x = torch.full((1, 3, 32, 32), 0.25)
    ll, highs = dwt2(x, 2)
    assert torch.allclose(ll, torch.full_like(ll, 1.0), atol=1e-6)  # gain sqrt(2)^4 = 4
    assert all(h.abs().max() < 1e-6 for lvl in highs for h in lvl)
    assert ll_subband(x.bfloat16()).dtype == torch.float32


def test_gradient_is_adjoint():
    x = torch.randn(1, 1, 8, 8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: ll_subband(t, 2), (x,), fast_mode=True)


@pytest.mark.parametrize("shape", [(3, 40, 24), (2, 3, 37, 50), (2, 2, 3, 16, 8), (1, 3, 2, 3)])
def test_ll_subband_is_dwt2s_ll(shape):
    """The LL-only path (half the correlations) equals dwt2's LL, for any leading dims and padded sizes."""
    x = torch.randn(*shape, dtype=torch.float64)
    for level in (1, 2):  # equal to rounding (the correlations' summation order may differ)
        torch.testing.assert_close(ll_subband(x, level), dwt2(x, level)[0], rtol=0, atol=1e-12)


def test_gradients_of_every_subband():
    x = torch.randn(2, 3, 12, 20, dtype=torch.float64, requires_grad=True)
    for pick in (lambda t: dwt2(t, 2)[0], lambda t: dwt2(t, 2)[1][0][1], lambda t: dwt2(t, 2)[1][1][2]):
        assert torch.autograd.gradcheck(pick, (x,), fast_mode=True)


def test_bad_input():
    with pytest.raises(TypeError, match="floating-point"):
        ll_subband(torch.zeros(1, 3, 8, 8, dtype=torch.uint8))
    with pytest.raises(ValueError, match="level"):
        ll_subband(torch.zeros(1, 3, 8, 8), 0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_is_exact_float32_even_with_tf32_allowed():
    """cuDNN may run float32 convolutions in TF32 (10-bit mantissa); the DWT's correlations never do, forward
    and backward, so CUDA matches the float64 transform to float32 rounding, and repeats bit for bit."""
    x = torch.rand(2, 3, 64, 48, dtype=torch.float64)
    prev = torch.backends.cudnn.allow_tf32, torch.backends.cudnn.deterministic
    torch.backends.cudnn.allow_tf32, torch.backends.cudnn.deterministic = True, False
    try:
        grads = []
        for _ in range(2):
            xc = x.float().cuda().requires_grad_(True)
            ll, highs = dwt2(xc, 2)
            (ll.square().sum() + highs[0][2].sum()).backward()
            grads.append(xc.grad)
        assert torch.backends.cudnn.allow_tf32 and not torch.backends.cudnn.deterministic  # restored
        assert torch.equal(grads[0], grads[1])  # deterministic algorithms whatever the caller's flags
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cudnn.deterministic = prev
    x64 = x.clone().requires_grad_(True)
    ll64, highs64 = dwt2(x64, 2)
    (ll64.square().sum() + highs64[0][2].sum()).backward()
    assert float((ll.double().cpu() - ll64).abs().max()) < 1e-5
    assert float((xc.grad.double().cpu() - x64.grad).abs().max()) < 1e-4
