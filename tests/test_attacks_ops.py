"""Tests for :mod:`gsw.attacks` (evaluation attacks on images and on Gaussians)."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from helpers import random_model
import torch
from PIL import Image

from gsw import attacks as A
from gsw.gaussians import Gaussians

H, W = 64, 48


def smooth_image(h: int = H, w: int = W, batch: int | None = None, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    b = 1 if batch is None else batch
    low = torch.rand(b, 3, h // 8, w // 8, generator=g)
    img = torch.nn.functional.interpolate(low, size=(h, w), mode="bilinear", align_corners=False)
    img = (0.8 * img + 0.2 * torch.rand(b, 3, h, w, generator=g)).clamp(0, 1)
    return img[0] if batch is None else img


def snapshot(g: Gaussians) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in g.parameters().items()}


def assert_untouched(g: Gaussians, snap: dict[str, torch.Tensor]) -> None:
    for k, v in g.parameters().items():
        assert torch.equal(v, snap[k]), k


# ------------------------------------------------------------------------------- shapes / range / seeds

CROP_HW = A.crop_size(H, W, 0.4)
SCALED_HW = A.scaled_size(H, W, 0.75)
EXPECTED_HW = {
    "noise": (H, W),
    "rotation": (H, W),
    "scaling": SCALED_HW,
    "blur": (H, W),
    "crop": CROP_HW,
    "jpeg": (H, W),
    "combined": CROP_HW,
    "brightness": (H, W),
    "contrast": (H, W),
}
OFFICIAL_HW = {"noise": (H, W), "blur": (H, W), "crop": A.crop_size(H, W, 0.5), "jpeg": (H, W)}


@pytest.mark.parametrize("name", sorted(A.IMAGE_ATTACKS))
@pytest.mark.parametrize("batched", [False, True])
def test_image_attack_shape_and_range(name, batched):
    img = smooth_image(batch=2 if batched else None)
    out = A.IMAGE_ATTACKS[name](img)
    lead = (2, 3) if batched else (3,)
    assert out.shape == lead + EXPECTED_HW[name]
    assert out.dtype == img.dtype
    assert out.min() >= 0 and out.max() <= 1
    assert torch.equal(img, smooth_image(batch=2 if batched else None))  # input untouched


@pytest.mark.parametrize("name", sorted(A.OFFICIAL_ATTACKS))
def test_official_attack_shape_and_range(name):
    out = A.OFFICIAL_ATTACKS[name](smooth_image())
    assert out.shape == (3,) + OFFICIAL_HW[name]
    assert out.min() >= 0 and out.max() <= 1


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


def test_sweeps():
    img = smooth_image()
    for name in A.SWEEPS:
        values = A.sweep(name)
        assert len(values) >= 4
        key = A.sweep_parameter(name)
        out = A.IMAGE_ATTACKS[name](img, **{key: values[2]})
        assert out.min() >= 0 and out.max() <= 1
    assert 0.1 in A.sweep("noise") and 50 in A.sweep("jpeg") and 0.4 in A.sweep("crop")
    assert 30.0 in A.sweep("rotation") and 0.75 in A.sweep("scaling")
    with pytest.raises(KeyError):
        A.sweep("nope")


# ------------------------------------------------------------------------------- model attacks


def test_parameter_noise():
    g = random_model(5000)
    snap = snapshot(g)
    out = A.parameter_noise(g, sigma=0.1, seed=0)
    assert_untouched(g, snap)
    for name in A.MODEL_FIELDS:
        d = getattr(out, name) - getattr(g, name)
        assert abs(d.std().item() - 0.1) < 0.005, name
        assert abs(d.mean().item()) < 0.005, name
    assert torch.equal(A.parameter_noise(g, seed=0).means, out.means)
    assert not torch.equal(A.parameter_noise(g, seed=1).means, out.means)
    only = A.parameter_noise(g, sigma=0.1, seed=0, fields=("sh",))
    assert torch.equal(only.means, g.means) and torch.equal(only.sh, out.sh)
    with pytest.raises(ValueError):
        A.parameter_noise(g, fields=("colors",))


def test_parameter_noise_attributes_leaves_positions_alone():
    g = random_model(5000)
    out = A.parameter_noise_attributes(g, sigma=0.1, seed=0)
    full = A.parameter_noise(g, sigma=0.1, seed=0)
    assert torch.equal(out.means, g.means)
    for name in ("log_scales", "quats", "opacity_logits", "sh"):
        assert torch.equal(getattr(out, name), getattr(full, name)), name  # same noise as the full attack
    assert A.MODEL_ATTACKS["parameter_noise_attributes"] is A.parameter_noise_attributes


@pytest.mark.parametrize("n", [1000, 7, 0])
def test_remove_random(n):
    g = random_model(n)
    snap = snapshot(g)
    out = A.remove_random(g, 0.2, seed=0)
    assert len(out) == n - math.floor(0.2 * n + 0.5)
    assert_untouched(g, snap)
    if n:
        # survivors are rows of the input, in their original order, without repeats
        idx = [int(torch.nonzero((g.means == m).all(1))[0, 0]) for m in out.means]
        assert idx == sorted(set(idx))
        assert not torch.equal(A.remove_random(g, 0.2, seed=1).means, out.means) or n < 5


def test_clone_random():
    g = random_model(1000)
    snap = snapshot(g)
    out = A.clone_random(g, 0.2, seed=0)
    assert len(out) == 1200
    assert_untouched(g, snap)
    for name, t in g.parameters().items():
        assert torch.equal(getattr(out, name)[:1000], t)
    # the clones are exact copies of distinct originals
    clones = out[1000:]
    idx = [int(torch.nonzero((g.means == m).all(1))[0, 0]) for m in clones.means]
    assert len(set(idx)) == 200
    assert torch.equal(clones.sh, g.sh[idx]) and torch.equal(clones.opacity_logits, g.opacity_logits[idx])
    out.means[0] += 1  # no aliasing with the input
    assert torch.equal(g.means, snap["means"])


def test_reduce_sh():
    g = random_model(100, degree=3)
    snap = snapshot(g)
    out = A.reduce_sh(g, 0)
    assert out.sh.shape == (100, 1, 3) and out.sh_degree == 0
    assert torch.equal(out.sh[:, 0], g.sh[:, 0])
    assert torch.equal(out.means, g.means)
    out.sh += 1
    assert_untouched(g, snap)
    assert A.reduce_sh(g, 1).sh.shape == (100, 4, 3)
    with pytest.raises(ValueError):
        A.reduce_sh(A.reduce_sh(g, 0), 2)


def test_prune_by_opacity():
    g = random_model(1001)
    snap = snapshot(g)
    out = A.prune_by_opacity(g, 0.5)
    assert_untouched(g, snap)
    assert len(out) == 1001 - 501
    threshold = torch.sort(g.opacity_logits).values[501]
    assert out.opacity_logits.min() >= threshold
    assert int((g.opacity_logits >= threshold).sum()) == len(out)


def test_quantize():
    g = random_model(2000)
    snap = snapshot(g)
    out = A.quantize(g, bits=8)
    assert_untouched(g, snap)
    for name, t in g.parameters().items():
        x = t.reshape(t.shape[0], -1).double()
        y = getattr(out, name).reshape(t.shape[0], -1).double()
        rng = x.max(0).values - x.min(0).values
        err = (y - x).abs().max(0).values
        bound = rng / 510 + 1e-6 * x.abs().max(0).values + 1e-7
        assert torch.all(err <= bound), name
        assert torch.all(err > 0), name  # it did quantise
        levels = torch.tensor([torch.unique(y[:, j]).numel() for j in range(y.shape[1])])
        assert int(levels.max()) <= 256
    const = Gaussians(
        means=torch.ones(4, 3), log_scales=torch.zeros(4, 3), quats=torch.ones(4, 4),
        opacity_logits=torch.zeros(4), sh=torch.zeros(4, 1, 3),
    )
    assert torch.equal(A.quantize(const).means, const.means)


# ------------------------------------------------------------------------------------- fine-tuning attack


@pytest.fixture(scope="module")
def tiny_scene():
    from gsw.scenes import default_scene

    return default_scene(width=32, height=32, n_cameras=4, detail=0.3)


def _renders(g, scene):
    from gsw.render.rasterize import rasterize

    return torch.stack([rasterize(g, c, background=scene.background).image.clamp(0, 1) for c in scene.cameras])


def test_finetune_moves_the_model_toward_jpeg_targets(tiny_scene):
    g, bg = tiny_scene.gaussians, tuple(tiny_scene.background.tolist())
    snap = {k: v.clone() for k, v in g.parameters().items()}
    before = _renders(g, tiny_scene)
    targets = A.jpeg(before, quality=10)
    out = A.finetune(g, tiny_scene.cameras, steps=40, quality=10, background=bg)
    after = _renders(out, tiny_scene)
    assert (after - targets).abs().mean() < 0.9 * (before - targets).abs().mean()
    assert all(torch.equal(v, snap[k]) for k, v in g.parameters().items())  # input untouched
    again = A.finetune(g, tiny_scene.cameras, steps=40, quality=10, background=bg)
    assert all(torch.equal(v, again.parameters()[k]) for k, v in out.parameters().items())  # deterministic


def test_finetune_on_plain_renders_keeps_the_model(tiny_scene):
    g, bg = tiny_scene.gaussians, tuple(tiny_scene.background.tolist())
    out = A.finetune(g, tiny_scene.cameras, steps=20, quality=None, background=bg)
    assert (_renders(out, tiny_scene) - _renders(g, tiny_scene)).abs().max() < 0.02


def test_bind_model_attacks(tiny_scene):
    bound = A.bind_model_attacks(["remove", "finetune"], tiny_scene.cameras)
    assert bound["remove"] is A.remove_random and bound["finetune"].keywords["cameras"] == tiny_scene.cameras
    with pytest.raises(KeyError, match="unknown model attacks"):
        A.bind_model_attacks(["finetuning"], tiny_scene.cameras)
    with pytest.raises(ValueError, match="steps"):
        A.finetune(tiny_scene.gaussians, tiny_scene.cameras, steps=0)
    with pytest.raises(ValueError, match="camera"):
        A.finetune(tiny_scene.gaussians, [])
