"""Tests for :mod:`gsw.attacks.ops` (deterministic image attacks)."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from PIL import Image

from gsw import attacks as A
from gsw.attacks import layers

H, W = 64, 48


def smooth_image(h: int = H, w: int = W, batch: int | None = None, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    b = 1 if batch is None else batch
    low = torch.rand(b, 3, h // 8, w // 8, generator=g)
    img = torch.nn.functional.interpolate(low, size=(h, w), mode="bilinear", align_corners=False)
    img = (0.8 * img + 0.2 * torch.rand(b, 3, h, w, generator=g)).clamp(0, 1)
    return img[0] if batch is None else img


# ------------------------------------------------------------------------------- shapes / range / seeds

@pytest.mark.parametrize("fn", [lambda x: A.brightness(x, 1.5), lambda x: A.contrast(x, 0.5),
                                lambda x: A.contrast(x, 2.0), lambda x: A.scaling(x, 0.75, resize_back=True)])
def test_other_attacks_keep_shape_and_range(fn):
    img = smooth_image()
    out = fn(img)
    assert out.shape == img.shape and out.min() >= 0 and out.max() <= 1


def test_brightness_contrast_identity():
    img = smooth_image()
    assert torch.allclose(A.brightness(img, 1.0), img)
    assert torch.allclose(A.contrast(img, 1.0), img, atol=1e-6)


@pytest.mark.parametrize("fn", [A.gaussian_noise, A.crop, A.combined])
def test_seeded_attacks_deterministic_and_seed_dependent(fn):
    img = smooth_image()
    a, b, c = fn(img, seed=1), fn(img, seed=1), fn(img, seed=2)
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_batch_element_matches_single_image():
    img = smooth_image(batch=2)
    assert torch.equal(A.crop(img, seed=3)[0], A.crop(img[0], seed=3))
    assert torch.equal(A.jpeg(img)[1], A.jpeg(img[1]))


def test_bad_inputs():
    with pytest.raises(ValueError):
        A.gaussian_noise(torch.rand(4, 8, 8))
    with pytest.raises(TypeError):
        A.jpeg(torch.zeros(3, 8, 8, dtype=torch.uint8))
    with pytest.raises(ValueError):
        A.crop(smooth_image(), keep_area=0.0)
    with pytest.raises(ValueError):
        A.jpeg(smooth_image(), quality=0)


# ------------------------------------------------------------------------------- individual image attacks


def test_noise_std():
    img = torch.full((3, 256, 256), 0.5)
    out = A.gaussian_noise(img, sigma=0.1, seed=0)
    d = out - img
    assert abs(d.mean().item()) < 2e-3
    assert abs(d.std().item() - 0.1) < 2e-3  # clamping at 0.5 +- 5 sigma is negligible
    assert abs((A.official_noise(img) - img).std().item() - 0.01) < 2e-4


def test_rotation_zero_is_identity():
    img = smooth_image()
    assert torch.allclose(A.rotation(img, 0.0), img, atol=1e-6)


def test_rotation_90_matches_rot90_square():
    img = smooth_image(40, 40)
    for deg, k in ((90.0, 1), (-90.0, -1), (180.0, 2)):
        out = A.rotation(img, deg)
        ref = torch.rot90(img, k, dims=(-2, -1))
        # exact (up to float rounding) on a square grid; compare the interior to avoid border effects
        assert torch.allclose(out[:, 1:-1, 1:-1], ref[:, 1:-1, 1:-1], atol=1e-5), deg


def test_rotation_fills_black():
    out = A.rotation(torch.ones(3, 32, 32), 45.0)
    assert out[:, 0, 0].abs().max() == 0  # corners come from outside the image
    assert torch.allclose(out[:, 16, 16], torch.ones(3))


def test_scaling_size():
    for h, w in ((64, 48), (101, 37)):
        out = A.scaling(torch.rand(3, h, w), 0.75)
        assert out.shape[-2:] == (round(h * 0.75), round(w * 0.75))
        assert A.scaling(torch.rand(3, h, w), 0.75, resize_back=True).shape[-2:] == (h, w)
    img = smooth_image()
    assert torch.allclose(A.scaling(img, 1.0), img, atol=1e-6)


def test_blur_kernel():
    for sigma, size in ((0.1, 3), (1.0, 7), (2.0, 13)):
        k = A.gaussian_kernel1d(sigma)
        assert k.numel() == size
        assert abs(k.sum().item() - 1.0) < 1e-12
        assert torch.allclose(k, k.flip(0))
    assert A.gaussian_kernel1d(1.0, kernel_size=3).numel() == 3


def test_blur_small_sigma_is_identity_and_preserves_constant():
    img = smooth_image()
    assert torch.allclose(A.gaussian_blur(img, sigma=1e-3), img, atol=1e-7)
    assert torch.allclose(A.gaussian_blur(img, sigma=0.1), img, atol=1e-6)
    const = torch.full((3, 20, 20), 0.3)
    assert torch.allclose(A.gaussian_blur(const, sigma=2.0), const, atol=1e-6)
    # a strong blur does change the image
    assert (A.gaussian_blur(img, sigma=2.0) - img).abs().mean() > 1e-3


def test_crop_area_and_aspect():
    for h, w, a in ((64, 48, 0.4), (100, 150, 0.4), (512, 512, 0.4), (64, 48, 0.5)):
        out = A.crop(torch.rand(3, h, w), keep_area=a, seed=0)
        ch, cw = out.shape[-2:]
        # rounding each side by at most 0.5 px
        tol = 0.5 * (ch + cw) / (h * w) + 0.25 / (h * w)
        assert abs(ch * cw / (h * w) - a) <= tol + 1e-12
        assert abs(ch / cw - h / w) <= 0.5 / cw + 0.5 * h / w / cw + 1e-12


def test_crop_is_a_window_of_the_input():
    img = torch.arange(3 * H * W, dtype=torch.float32).reshape(3, H, W) / (3 * H * W)
    out = A.crop(img, seed=5)
    top = int(torch.nonzero(img[0] == out[0, 0, 0])[0, 0])
    left = int(torch.nonzero(img[0] == out[0, 0, 0])[0, 1])
    assert torch.equal(out, img[:, top : top + out.shape[1], left : left + out.shape[2]])
    positions = {tuple(A.crop(img, seed=s)[0, 0, 0].reshape(1).tolist()) for s in range(10)}
    assert len(positions) > 1


def test_official_crop_is_centred():
    img = torch.rand(3, 40, 40)
    out = A.official_crop(img)
    h, w = A.crop_size(40, 40, 0.5)
    assert torch.equal(out, img[:, (40 - h) // 2 : (40 - h) // 2 + h, (40 - w) // 2 : (40 - w) // 2 + w])


@pytest.mark.parametrize("quality,subsampling", [(50, "4:2:0"), (10, "4:2:0"), (90, "4:4:4")])
def test_jpeg_equals_pil_round_trip(quality, subsampling):
    img = smooth_image()
    u8 = A.to_uint8(img).permute(1, 2, 0).numpy()
    buf = io.BytesIO()
    Image.fromarray(u8).save(buf, format="JPEG", quality=quality, subsampling=subsampling)
    ref = np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB"))
    out = A.jpeg(img, quality=quality, subsampling=subsampling)
    got = A.to_uint8(out).permute(1, 2, 0).numpy()
    assert np.array_equal(got, ref)
    assert torch.equal(out * 255, (out * 255).round())  # exact multiples of 1/255
    assert not np.array_equal(got, u8)  # it did compress


def test_blur_kernel_values():
    for sigma, size in ((0.7, 5), (1.3, 9)):
        t = torch.arange(size, dtype=torch.float64) - size // 2
        want = torch.exp(-(t**2) / (2 * sigma**2))
        torch.testing.assert_close(A.gaussian_kernel1d(sigma, size), want / want.sum(), rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match="odd"):
        A.gaussian_kernel1d(1.0, kernel_size=4)


@pytest.mark.parametrize("sigma", [0.5, 1.0, 2.0])
def test_one_blur_for_evaluation_and_training(sigma):
    """ops.gaussian_blur, the training layer and GpuAttacks.blur are the same blur (kernel and padding)."""
    x = 0.1 + 0.8 * smooth_image(batch=2)  # inside (0, 1): the evaluation blur's clamp does nothing
    ops_out = A.gaussian_blur(x, sigma=sigma)
    layer_out = layers.GaussianBlur(sigma=(sigma, sigma), fixed=True)(x)
    gpu_out = layers.GpuAttacks(torch.device("cpu"), 0).blur(x, 1.0, sigma=(sigma, sigma))
    assert torch.equal(ops_out, layer_out) and torch.equal(ops_out, gpu_out)
    assert (ops_out - x).abs().mean() > 1e-3  # it did blur


def test_training_jpeg_is_the_evaluation_jpeg():
    x = smooth_image(batch=3)
    real = layers.real_jpeg(x, torch.tensor([90.0, 50.0, 10.0]))
    for i, q in enumerate((90, 50, 10)):
        assert torch.equal(real[i], A.jpeg(x[i], quality=q))


def test_combined_defaults_are_the_single_attacks_defaults():
    img = smooth_image(batch=2)
    assert torch.equal(A.combined(img, seed=4), A.jpeg(A.gaussian_blur(A.crop(img, seed=4))))
