"""Tests for gsw.scenes.synthetic: determinism, ranges and geometry of the generated scenes."""

from __future__ import annotations

import math

import pytest
import torch

from gsw.camera import Camera
from gsw.constants import SH_C0
from gsw.gaussians import Gaussians
from gsw.scenes import (
    DEFAULT_SCENE_CENTER,
    default_cameras,
    default_scene,
    frustum_scene,
    frustum_sigma_px,
    random_gaussians,
)


def same(a: Gaussians, b: Gaussians) -> bool:
    return all(torch.equal(t, b.parameters()[k]) for k, t in a.parameters().items())


def test_random_gaussians_deterministic_and_seeded():
    a = random_gaussians(300, seed=1)
    torch.manual_seed(123)  # the global RNG must not matter
    torch.rand(10)
    b = random_gaussians(300, seed=1)
    assert same(a, b)
    assert not torch.equal(a.means, random_gaussians(300, seed=2).means)
    c = random_gaussians(300, seed=1, dtype=torch.float64)
    assert c.dtype == torch.float64 and same(c.to(dtype=torch.float32), a)


def test_random_gaussians_ranges():
    g = random_gaussians(
        2000, sh_degree=1, seed=0, extent=2.0, scale_range=(0.02, 0.2), opacity_range=(0.3, 0.6)
    )
    assert len(g) == 2000 and g.sh_degree == 1
    g.check_finite()
    assert g.means.abs().max() <= 2.0 and g.means.abs().max() > 1.9
    assert g.scales.min() >= 0.02 * (1 - 1e-6) and g.scales.max() <= 0.2 * (1 + 1e-6)
    assert g.opacities.min() >= 0.3 - 1e-6 and g.opacities.max() <= 0.6 + 1e-6
    rgb = 0.5 + SH_C0 * g.sh[:, 0]
    assert rgb.min() >= -1e-6 and rgb.max() <= 1 + 1e-6
    with pytest.raises(ValueError):
        random_gaussians(10, opacity_range=(0.0, 0.5))


def test_frustum_sigma_px():
    # 100k Gaussians at 800x800: ~2.85 px sigma, i.e. a 3-sigma footprint of ~8.6 px.
    assert frustum_sigma_px(100_000, 800, 800) == pytest.approx(2.854, abs=1e-3)
    assert frustum_sigma_px(400_000, 800, 800) == pytest.approx(frustum_sigma_px(100_000, 800, 800) / 2)


def test_frustum_scene_fills_the_frustum():
    cam = Camera.look_at((1.0, -6.0, 2.0), (0.0, 0.0, 0.5), (0.0, 0.0, 1.0), math.radians(60), 200, 150)
    n = 20_000
    g = frustum_scene(n, cam, seed=4, depth_range=(2.0, 10.0))
    assert len(g) == n and g.sh_degree == 3
    g.check_finite()
    px, depth = cam.project(g.means.double())
    assert depth.min() >= 2.0 - 1e-4 and depth.max() <= 10.0 + 1e-4
    assert px.min() >= -1e-3 and px[:, 0].max() <= 200 + 1e-3 and px[:, 1].max() <= 150 + 1e-3
    # Uniform in volume: the fraction beyond the middle depth is (10^3 - 6^3) / (10^3 - 2^3).
    frac = float((depth > 6.0).double().mean())
    assert frac == pytest.approx((1000 - 216) / (1000 - 8), abs=0.02)
    # Projected size: geometric mean of sigma * f / z matches frustum_sigma_px within 10%.
    sigma_px = (g.log_scales.double().mean(1) + math.log(cam.fx) - depth.log()).mean().exp()
    assert float(sigma_px) == pytest.approx(frustum_sigma_px(n, 200, 150), rel=0.1)
    # DC-dominant SH, N(0, 1)-ish opacity logits.
    assert g.sh[:, 0].abs().mean() > 5 * g.sh[:, 1:].abs().mean()
    assert abs(float(g.opacity_logits.std()) - 1.0) < 0.05
    assert same(g, frustum_scene(n, cam, seed=4, depth_range=(2.0, 10.0)))
    assert not torch.equal(g.means, frustum_scene(n, cam, seed=5).means)


def test_default_scene():
    scene = default_scene(n_cameras=6, width=64, height=48, sh_degree=2)
    g = scene.gaussians
    assert 15_000 < len(g) < 40_000 and g.sh_degree == 2
    g.check_finite()
    assert scene.background.shape == (3,) and scene.background.dtype == g.dtype
    rgb = 0.5 + SH_C0 * g.sh[:, 0]
    assert rgb.min() >= -1e-5 and rgb.max() <= 1 + 1e-5
    assert len(rgb.round(decimals=2).unique(dim=0)) >= 6  # several textures
    assert g.means[:, 2].min() > -0.05  # nothing below the ground
    assert g.opacities.min() > 0.85
    assert len(scene.cameras) == 6 and (scene.cameras[0].width, scene.cameras[0].height) == (64, 48)
    center = torch.tensor(DEFAULT_SCENE_CENTER, dtype=torch.float64)[None]
    for cam in scene.cameras:
        px, depth = cam.project(center)
        torch.testing.assert_close(px[0], torch.tensor([32.0, 24.0], dtype=torch.float64))
        _, d = cam.project(g.means.double())
        assert d.min() > 0.5  # every Gaussian in front of every camera
    again = default_scene(n_cameras=6, width=64, height=48, sh_degree=2)
    assert same(g, again.gaussians)
    other = default_scene(n_cameras=6, width=64, height=48, sh_degree=2, seed=1)
    assert len(other.gaussians) == len(g) and not torch.equal(other.gaussians.means, g.means)
    assert len(default_scene(detail=0.5).gaussians) < len(g) / 3


def test_default_cameras():
    cams = default_cameras(4, 32, 32)
    assert len(cams) == 4
    assert all(torch.equal(a.viewmat, b.viewmat) for a, b in zip(cams, default_cameras(4, 32, 32)))
