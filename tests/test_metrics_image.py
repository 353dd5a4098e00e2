"""PSNR / SSIM helpers."""

from __future__ import annotations

import math

import pytest
import torch

from gsw.metrics.image import mse, psnr, ssim, ssim_loss


def test_psnr_known_value():
    a = torch.zeros(3, 8, 8)
    b = torch.full((3, 8, 8), 0.1)
    assert float(psnr(a, b)) == pytest.approx(20.0, abs=1e-4)
    assert float(mse(a, b)) == pytest.approx(0.01)
    assert math.isinf(float(psnr(a, a)))
    batch = psnr(torch.stack([a, a]), torch.stack([b, a + 0.01]))
    assert batch.shape == (2,) and float(batch[1]) == pytest.approx(40.0, abs=1e-3)


def test_psnr_formula_and_data_range():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(2, 3, 16, 16, generator=g)
    b = (a + 0.05 * torch.randn(a.shape, generator=g)).clamp(0, 1)
    want = -10 * torch.log10(((a.double() - b.double()) ** 2).flatten(1).mean(1))
    torch.testing.assert_close(psnr(a, b).double(), want, rtol=0, atol=1e-4)
    torch.testing.assert_close(psnr(255 * a, 255 * b, data_range=255.0), psnr(a, b), rtol=0, atol=1e-4)


def test_ssim_properties():
    torch.manual_seed(0)
    a = torch.rand(3, 32, 32)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-5)
    noisy = (a + 0.2 * torch.randn_like(a)).clamp(0, 1)
    s = float(ssim(a, noisy))
    assert 0.0 < s < 0.9
    assert float(ssim(a, noisy)) == pytest.approx(float(ssim(noisy, a)), abs=1e-6)
    assert ssim(torch.stack([a, a]), torch.stack([a, noisy])).shape == (2,)
    assert ssim(a, noisy, reduce=False).shape == (1, 3, 32, 32)


def test_ssim_loss_differentiable():
    a = torch.rand(3, 16, 16, requires_grad=True)
    b = torch.rand(3, 16, 16)
    loss = ssim_loss(a, b)
    loss.backward()
    assert a.grad is not None and torch.isfinite(a.grad).all() and float(loss.detach()) > 0


def test_shape_errors():
    with pytest.raises(ValueError, match="differ"):
        psnr(torch.zeros(3, 4, 4), torch.zeros(3, 4, 5))
    with pytest.raises(ValueError, match="expected"):
        ssim(torch.zeros(4, 4), torch.zeros(4, 4))
