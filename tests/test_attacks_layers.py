"""Noise layers: shapes, ranges, seeded determinism, gradients, JPEG fidelity."""

import pytest
import torch

from gsw.attacks import layers as N
from gsw.attacks.presets import IMAGE_ATTACKS, PAPER_IMAGE_ATTACKS


def _img(b=4, h=64, w=48, seed=0):
    g = torch.Generator().manual_seed(seed)
    base = torch.rand(b, 3, h // 8, w // 8, generator=g)
    return torch.nn.functional.interpolate(base, size=(h, w), mode="bilinear", align_corners=False)


@pytest.mark.parametrize("name", list(N.training_noise_layers().keys()))
def test_training_layers_shape_range_determinism_and_gradient(name):
    x = _img().requires_grad_(True)
    layer = N.training_noise_layers()[name]
    y1 = layer(x, generator=torch.Generator().manual_seed(3))
    y2 = layer(x, generator=torch.Generator().manual_seed(3))
    assert y1.shape[:2] == x.shape[:2] and y1.shape[-1] >= 4
    assert torch.equal(y1, y2)
    assert float(y1.min()) >= -1e-4 and float(y1.max()) <= 1 + 1e-4
    y1.sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    if name != "identity":
        assert x.grad.abs().sum() > 0


@pytest.mark.parametrize("name", list(N.paper_attacks().keys()))
def test_paper_attacks_run(name):
    y = N.paper_attacks()[name](_img(2), generator=torch.Generator().manual_seed(0))
    assert y.shape[:2] == (2, 3)


def test_fixed_parameters_and_strength():
    x = _img(2, 64, 64)
    assert N.Crop(area=(0.25, 0.25), fixed=True)(x).shape[-2:] == (32, 32)
    assert N.Resize(scale=(0.75, 0.75), fixed=True)(x).shape[-2:] == (48, 48)
    layer = N.GaussianNoise(std=(0.0, 0.5))
    layer.strength = 0.0
    assert torch.allclose(layer(x, generator=torch.Generator().manual_seed(0)), x)
    assert torch.allclose(N.Rotation(degrees=(0.0, 0.0), fixed=True)(x), x, atol=1e-5)
    c = torch.full((1, 3, 32, 32), 0.3)
    assert torch.allclose(N.GaussianBlur(sigma=(2.0, 2.0), fixed=True)(c), c, atol=1e-6)


def test_jpeg_real_vs_differentiable():
    x = _img(2, 64, 64)
    q = torch.tensor([50.0, 50.0])
    real, diff = N.real_jpeg(x, q), N.diff_jpeg(x, q)
    mse = lambda a, b: float((a - b).pow(2).mean())  # noqa: E731
    assert mse(real, x) > 1e-6  # it does compress
    assert mse(diff, real) < mse(real, x)  # the differentiable codec is closer to real JPEG than to x
    st = N.JPEG((50, 50), mode="real_diffgrad", fixed=True)
    xg = x.clone().requires_grad_(True)
    y = st(xg)
    assert torch.allclose(y, real, atol=1e-6)  # forward pass is the real codec
    y.sum().backward()
    assert xg.grad.abs().sum() > 0
    assert torch.equal(N.quantize_st(torch.tensor([0.6 / 255, 1.2])), torch.tensor([1 / 255, 1.0]))


def test_paper_layers_are_the_presets_strengths():
    p = PAPER_IMAGE_ATTACKS
    want = {N.GaussianNoise: p["noise"]["sigma"], N.Rotation: p["rotation"]["degrees"],
            N.Resize: p["scaling"]["factor"], N.GaussianBlur: p["blur"]["sigma"], N.Crop: p["crop"]["keep_area"],
            N.JPEG: p["jpeg"]["quality"]}
    layers = list(N.paper_attacks().values())
    singles = {type(layer): layer for layer in layers if not isinstance(layer, N.Combined)}
    assert len(singles) == len(layers) - 1 and set(singles) == set(want)
    for kind, layer in singles.items():
        assert layer.fixed and layer.weakest == layer.strongest == want[kind], kind.__name__
    (combined,) = [layer for layer in layers if isinstance(layer, N.Combined)]
    c = p["combined"]
    assert [(type(layer), layer.strongest) for layer in combined.layers] == [
        (N.Crop, c["keep_area"]), (N.GaussianBlur, c["blur_sigma"]), (N.JPEG, c["quality"])]
    # where the conventions agree, the layer is the evaluation attack at the paper's strength
    x = 0.1 + 0.8 * _img(2)
    assert torch.equal(singles[N.GaussianBlur](x), IMAGE_ATTACKS["blur"](x))
    torch.testing.assert_close(singles[N.JPEG](x), IMAGE_ATTACKS["jpeg"](x), rtol=0, atol=1e-6)
    torch.testing.assert_close(singles[N.Resize](x), IMAGE_ATTACKS["scaling"](x), rtol=0, atol=1e-6)


def test_matched_noise_layers_reach_the_paper_strengths_and_are_seeded():
    from gsw.attacks.layers import matched_noise_layers
    from gsw.attacks.presets import PAPER_IMAGE_ATTACKS

    layers = matched_noise_layers(jpeg_mode="real")
    assert layers["noise"].strongest == PAPER_IMAGE_ATTACKS["noise"]["sigma"]
    assert layers["rotation"].strongest == PAPER_IMAGE_ATTACKS["rotation"]["degrees"]
    assert layers["crop"].strongest == PAPER_IMAGE_ATTACKS["crop"]["keep_area"]
    assert layers["jpeg"].strongest == PAPER_IMAGE_ATTACKS["jpeg"]["quality"]
    x = torch.rand(2, 3, 48, 48)
    for name, layer in layers.items():
        a = layer(x, generator=torch.Generator().manual_seed(4))
        b = layer(x, generator=torch.Generator().manual_seed(4))
        assert torch.equal(a, b), name
