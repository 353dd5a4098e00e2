"""PCA whitening: zero mean / identity covariance on the fitting set, fit from a decoder, errors."""

import pytest
import torch

from gsw.decoder import HiddenDecoder, WhiteningLayer, fit_whitening, ll_subband


def _correlated(n=2000, k=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, k, generator=g) @ torch.randn(k, k, generator=g) + 5 * torch.randn(k, generator=g)


@pytest.mark.parametrize("mode", ["pca", "zca"])
def test_whitening_gives_zero_mean_identity_covariance(mode):
    x = _correlated().double()
    layer = WhiteningLayer(16).double().fit(x, mode=mode)
    y = layer(x)
    assert y.mean(0).abs().max() < 1e-9
    cov = (y - y.mean(0)).T @ (y - y.mean(0)) / (x.shape[0] - 1)
    assert torch.allclose(cov, torch.eye(16, dtype=torch.float64), atol=1e-6)
    assert not list(layer.parameters())  # frozen: buffers only


def test_zca_is_symmetric_and_pca_is_rotation_of_it():
    x = _correlated(k=8).double()
    pca, zca = WhiteningLayer(8).double().fit(x, "pca"), WhiteningLayer(8).double().fit(x, "zca")
    assert torch.allclose(zca.weight, zca.weight.T, atol=1e-8)
    r = pca.weight @ torch.linalg.inv(zca.weight)
    assert torch.allclose(r @ r.T, torch.eye(8, dtype=torch.float64), atol=1e-6)


def test_median_centering_splits_every_bit_in_half_on_heavy_tails():
    g = torch.Generator().manual_seed(3)
    x = torch.randn(1001, 6, generator=g, dtype=torch.float64).exp() ** 3  # heavy right tail
    mean_c = WhiteningLayer(6).double().fit(x, "zca")
    med_c = WhiteningLayer(6).double().fit(x, "zca", center="median")
    p1_mean = (mean_c(x) > 0).double().mean(0)
    p1_med = (med_c(x) > 0).double().mean(0)
    assert (p1_mean - 0.5).abs().max() > 0.2  # the mean leaves most samples below zero
    assert (p1_med - 0.5).abs().max() <= 1 / 1001  # the median: half above, half below
    assert torch.allclose(med_c.weight, mean_c.weight)  # same decorrelating map, only the offset moves
    y = med_c(x)
    cov = (y - y.mean(0)).T @ (y - y.mean(0)) / 1000
    assert torch.allclose(cov, torch.eye(6, dtype=torch.float64), atol=1e-6)


def test_fit_whitening_from_decoder():
    torch.manual_seed(0)
    dec = HiddenDecoder(8, num_blocks=2, channels=8)
    batches = [ll_subband(torch.rand(32, 3, 32, 32)) for _ in range(4)]
    layer, raw = fit_whitening(dec, batches, 8)
    assert raw.shape == (128, 8)
    y = layer(raw)  # float32 buffers: agreement to float32 precision of an ill-conditioned map
    assert y.mean(0).abs().max() < 2e-3
    cov = (y - y.mean(0)).T @ (y - y.mean(0)) / 127
    assert torch.allclose(cov, torch.eye(8), atol=1e-2)


def test_errors():
    with pytest.raises(ValueError):
        WhiteningLayer(8).fit(torch.randn(5, 8))  # too few samples
    with pytest.raises(ValueError):
        WhiteningLayer(8).fit(torch.randn(50, 4))
    with pytest.raises(ValueError):
        WhiteningLayer(4).fit(torch.randn(50, 4), mode="nope")
    with pytest.raises(ValueError, match="center"):
        WhiteningLayer(4).fit(torch.randn(50, 4), center="mode")
