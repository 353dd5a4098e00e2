"""Viewpoint sampler (gsw.mark.views): cameras around the content, outside its core, deterministic."""

from __future__ import annotations

import math
import random

import pytest
import torch
from helpers import random_model

from gsw.camera import orbit_cameras
from gsw.gaussians import Gaussians, cat_gaussians
from gsw.mark.views import ViewSampler, ViewSamplerConfig, content_bounds, gap_views, scale_camera
from gsw.render.rasterize import rasterize


def _scene(n: int = 2000, seed: int = 0) -> Gaussians:
    g = random_model(n, degree=1, seed=seed)
    return Gaussians(g.means * 0.5 + torch.tensor([3.0, -2.0, 1.0]), g.log_scales, g.quats,
                     torch.full((n,), 2.0), g.sh)


def _check_looks_at_content(cams, centre, radius):
    for cam in cams:
        uv, depth = cam.project(centre[None].float())
        assert depth[0] > 0, cam.name
        assert 0 <= uv[0, 0] <= cam.width and 0 <= uv[0, 1] <= cam.height, (cam.name, uv.tolist())
        assert float((cam.center.double() - centre).norm()) > radius, cam.name


def test_content_bounds_is_robust_to_faint_far_outliers():
    g = _scene()
    centre, radius = content_bounds(g)
    assert torch.allclose(centre, torch.tensor([3.0, -2.0, 1.0], dtype=torch.float64), atol=0.1)
    assert 0.5 < radius < 2.0
    outliers = Gaussians(torch.full((40, 3), 500.0), torch.zeros(40, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(40, 1),
                         torch.full((40,), -6.0), torch.zeros(40, 4, 3))
    c2, r2 = content_bounds(cat_gaussians([g, outliers]))
    assert float((c2 - centre).norm()) < 0.05 and abs(r2 - radius) < 0.1 * radius


@pytest.mark.parametrize("with_cameras", [True, False])
def test_sampled_cameras_look_at_the_content_from_outside(with_cameras):
    g = _scene()
    centre, radius = content_bounds(g)
    cams = orbit_cameras(centre.tolist(), 4.0, 8, width=96, height=64) if with_cameras else None
    sampled = ViewSampler(g, cams, seed=3).sample_many(60)
    _check_looks_at_content(sampled, centre, radius)
    modes = {c.name for c in sampled}
    assert modes == ({"sampled_jitter", "sampled_interpolate", "sampled_orbit"} if with_cameras else {"sampled_orbit"})
    sizes = {(c.width, c.height) for c in sampled}
    assert len(sizes) > 10 and all(max(s) <= ViewSamplerConfig.max_side for s in sizes)


def test_orbit_elevations_stay_in_range():
    g = _scene()
    centre, _ = content_bounds(g)
    cfg = ViewSamplerConfig(modes=(("orbit", 1.0),), elevation_deg=(10.0, 40.0))
    for cam in ViewSampler(g, None, cfg, seed=1).sample_many(40):
        d = cam.center.double() - centre
        el = math.degrees(math.asin(float(d[2] / d.norm())))
        assert 10.0 - 1e-6 <= el <= 40.0 + 1e-6


def test_sampler_is_deterministic_under_a_seed():
    g = _scene()
    cams = orbit_cameras([3.0, -2.0, 1.0], 4.0, 6, width=64, height=64)
    a = ViewSampler(g, cams, seed=7).sample_many(10)
    b = ViewSampler(g, cams, seed=7).sample_many(10)
    c = ViewSampler(g, cams, seed=8).sample_many(10)
    assert all(torch.equal(x.viewmat, y.viewmat) and (x.fx, x.width, x.cx) == (y.fx, y.width, y.cx)
               for x, y in zip(a, b))
    assert any(not torch.equal(x.viewmat, y.viewmat) for x, y in zip(a, c))


def test_a_reseeded_sampler_draws_a_fresh_samplers_sequence():
    g = _scene()
    cams = orbit_cameras([3.0, -2.0, 1.0], 4.0, 6, width=64, height=64)
    base = ViewSampler(g, cams, seed=1)
    base.sample_many(3)  # the base's own draws do not move a reseeded copy's
    a = base.reseeded(7).sample_many(10)
    b = ViewSampler(g, cams, seed=7).sample_many(10)
    assert all(torch.equal(x.viewmat, y.viewmat) and (x.fx, x.width, x.cx) == (y.fx, y.width, y.cx)
               for x, y in zip(a, b))


def test_gap_views_lie_between_neighbouring_cameras():
    g = _scene()
    centre, radius = content_bounds(g)
    cams = orbit_cameras(centre.tolist(), 4.0, 8, width=96, height=64)  # a ring of 8
    gaps = gap_views(g, cams, 24, seed=5)
    _check_looks_at_content(gaps, centre, radius)
    given = torch.stack([c.center.double() - centre for c in cams])
    given = given / given.norm(dim=1, keepdim=True)
    apart = math.degrees(math.acos(float(given[0] @ given[1])))  # neighbours' angle from the centre
    for cam in gaps:
        d = cam.center.double() - centre
        angles = torch.rad2deg(torch.arccos((given @ (d / d.norm())).clamp(-1, 1)))
        nearest, second = angles.sort().values[:2].tolist()
        # on the arc between two neighbours, a quarter to half of the way from the nearer
        assert 0.25 * apart - 1e-3 <= nearest <= 0.5 * apart + 1e-3
        assert nearest + second == pytest.approx(apart, abs=1e-3)
        assert (cam.width, cam.height, cam.fx) == (96, 64, pytest.approx(cams[0].fx))  # the cameras' own lens
    again = gap_views(g, cams, 24, seed=5)
    assert all(torch.equal(a.viewmat, b.viewmat) for a, b in zip(gaps, again))
    assert not torch.equal(gap_views(g, cams, 1, seed=6)[0].viewmat, gaps[0].viewmat)
    with pytest.raises(ValueError, match="at least 2"):
        gap_views(g, cams[:1], 4)


def test_config_rejects_bad_ranges():
    with pytest.raises(ValueError, match="size_range"):
        ViewSamplerConfig(size_range=(2.0, 1.0))
    with pytest.raises(ValueError, match="modes"):
        ViewSamplerConfig(modes=(("spiral", 1.0),))
    with pytest.raises(ValueError, match="elevation"):
        ViewSamplerConfig(elevation_deg=(-90.0, 10.0))


def test_scale_camera_crop_renders_a_window_of_the_large_image():
    g = _scene(600)
    cam = orbit_cameras([3.0, -2.0, 1.0], 4.0, 1, width=40, height=32)[0]
    full = rasterize(g, scale_camera(cam, 2.0)).image
    crop_cam = scale_camera(cam, 2.0, max_side=48, rng=random.Random(0))
    assert (crop_cam.width, crop_cam.height) == (48, 48)
    ox, oy = round(cam.cx * 2 - crop_cam.cx), round(cam.cy * 2 - crop_cam.cy)
    window = full[:, oy:oy + crop_cam.height, ox:ox + crop_cam.width]
    # equal up to the rasterizer's frustum-dependent clamp of projected centres (INRIA's 1.3 tan(fov / 2))
    diff = (rasterize(g, crop_cam).image - window).abs()
    assert float(diff.mean()) < 1e-3 and float(diff.max()) < 0.05
