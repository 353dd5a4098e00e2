"""The C++ CPU kernels against the pure-PyTorch reference, gradcheck, contribution, edge cases."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys

import pytest
from helpers import SHARED_DATA, require
import torch

import gsw
from gsw.camera import Camera
from gsw.gaussians import Gaussians
from gsw.render.rasterize import (Projection, bin_gaussians, blend, contribution, project,
                                  rasterize)
from gsw.render._reference import reference_contribution, reference_rasterize
from gsw.scenes import frustum_scene, heavy_scene, random_gaussians

FIXTURE = SHARED_DATA / "ply" / "sh3_fixture" / "point_cloud.ply"


def make_camera(width: int = 40, height: int = 30, *, distance: float = 3.0, dtype=torch.float32,
                cx: float | None = None, cy: float | None = None, fov_x: float = 0.9) -> Camera:
    cam = Camera.look_at((0.3, -distance, 0.4), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), fov_x, width, height)
    if cx is not None or cy is not None:
        cam = Camera(viewmat=cam.viewmat, fx=cam.fx, fy=cam.fy, cx=cam.cx if cx is None else cx,
                     cy=cam.cy if cy is None else cy, width=width, height=height)
    return Camera(viewmat=cam.viewmat.to(dtype), fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy,
                  width=cam.width, height=cam.height)


def ref_render(g: Gaussians, cam: Camera, sh_degree: int, background: torch.Tensor):
    return reference_rasterize(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, cam.viewmat,
                               cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, sh_degree,
                               background)


def assert_forward_matches(g: Gaussians, cam: Camera, *, sh_degree: int | None = None,
                           background=(0.0, 0.0, 0.0), atol: float = 1e-5) -> None:
    degree = g.sh_degree if sh_degree is None else sh_degree
    bg = torch.tensor(background, dtype=g.dtype)
    out = rasterize(g, cam, sh_degree=degree, background=bg)
    ref = ref_render(g, cam, degree, bg)
    assert torch.equal(out.radii, ref.projection.radii)
    assert (out.image - ref.image).abs().max().item() <= atol
    assert (out.alpha - ref.alpha).abs().max().item() <= atol
    assert (out.depth - ref.depth).abs().max().item() <= atol * max(1.0, float(out.depth.abs().max()))
    assert (out.final_T - ref.final_T).abs().max().item() <= atol
    vis = out.visible
    assert torch.allclose(out.means2d[vis], ref.projection.means2d[vis], atol=1e-4, rtol=1e-5)
    assert torch.equal(out.n_contrib, ref.n_contrib)


# ----------------------------------------------------------------------------------------- forward


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
@pytest.mark.parametrize("seed", [0, 1])
def test_forward_matches_reference_random(sh_degree: int, seed: int) -> None:
    g = random_gaussians(120, sh_degree=sh_degree, seed=seed, extent=0.8, scale_range=(0.02, 0.15))
    assert_forward_matches(g, make_camera())


@pytest.mark.parametrize("size", [(16, 16), (17, 33), (50, 21), (1, 1), (64, 48)])
def test_forward_sizes_not_multiple_of_16(size: tuple[int, int]) -> None:
    g = random_gaussians(80, sh_degree=1, seed=3, extent=0.8)
    assert_forward_matches(g, make_camera(*size))


def test_forward_background_and_off_centre_principal_point() -> None:
    g = random_gaussians(60, sh_degree=2, seed=4, extent=0.5, opacity_range=(0.05, 0.5))
    assert_forward_matches(g, make_camera(37, 29, cx=11.3, cy=20.1), background=(0.2, 0.5, 0.9))


def test_forward_lower_sh_degree_than_stored() -> None:
    g = random_gaussians(60, sh_degree=3, seed=5)
    assert_forward_matches(g, make_camera(), sh_degree=1)


@pytest.mark.parametrize("size", [(16, 16), (50, 21), (1, 1)])
def test_tile_walks_are_each_tiles_largest_n_contrib(size: tuple[int, int]) -> None:
    W, H = size
    out = rasterize(random_gaussians(200, sh_degree=0, seed=9, extent=0.8), make_camera(W, H), validate=False)
    walks = out.tile_walks()
    tx, ty = -(-W // 16), -(-H // 16)
    expected = [int(out.n_contrib[y * 16:(y + 1) * 16, x * 16:(x + 1) * 16].max())
                for y in range(ty) for x in range(tx)]
    assert walks.dtype == torch.int64 and walks.tolist() == expected
    assert int(walks.max()) > 0


def test_empty_scene_is_background() -> None:
    g = Gaussians.empty(sh_degree=2)
    out = rasterize(g, make_camera(21, 13), background=(0.1, 0.2, 0.3))
    assert out.image.shape == (3, 13, 21)
    assert torch.allclose(out.image, torch.tensor([0.1, 0.2, 0.3]).view(3, 1, 1).expand(3, 13, 21))
    assert out.alpha.abs().max() == 0 and out.n_contrib.max() == 0


def test_everything_culled_behind_camera_and_at_near_plane() -> None:
    from gsw.constants import NEAR_PLANE

    cam = make_camera()
    g = random_gaussians(30, sh_degree=0, seed=6, extent=0.2)
    # Put everything behind the camera, and a few at the near plane.
    cam_pos = cam.center.to(g.dtype)
    forward = cam.R[2].to(g.dtype)
    g.means = cam_pos - forward * torch.linspace(0.1, 2.0, 30).unsqueeze(1)
    g.means[:5] = cam_pos + forward * (NEAR_PLANE - 1e-4)  # just inside the culled side
    out = rasterize(g, cam, background=(1.0, 1.0, 1.0))
    assert int(out.visible.sum()) == 0
    assert torch.all(out.image == 1.0)
    assert_forward_matches(g, cam, background=(1.0, 1.0, 1.0))


def test_near_plane_straddling_and_off_screen() -> None:
    from gsw.constants import NEAR_PLANE

    cam = make_camera(48, 32)
    g = random_gaussians(80, sh_degree=1, seed=7, extent=0.6)
    forward = cam.R[2].to(g.dtype)
    right = cam.R[0].to(g.dtype)
    g.means[:10] = cam.center.to(g.dtype) + forward * (NEAR_PLANE + torch.linspace(-0.05, 0.05, 10)).unsqueeze(1)
    g.means[10:20] = g.means[10:20] + right * 5.0  # far off-screen to the side
    assert_forward_matches(g, cam)


def test_tile_border_straddling_splats() -> None:
    # Splats centred exactly on tile borders (pixel 16, 32 ...) in a 64x48 image.
    cam = make_camera(64, 48)
    n = 12
    px = torch.tensor([16.0, 32.0, 48.0, 16.0, 32.0, 48.0] * 2)
    py = torch.tensor([16.0] * 6 + [32.0] * 6)
    depth = torch.linspace(2.5, 3.5, n)
    pts_cam = torch.stack([(px - cam.cx) / cam.fx * depth, (py - cam.cy) / cam.fy * depth, depth], 1)
    means = (pts_cam - cam.t.float()) @ cam.R.float()  # camera -> world: R^T (p - t)
    g = random_gaussians(n, sh_degree=0, seed=8, scale_range=(0.03, 0.08))
    g.means = means.contiguous()
    assert_forward_matches(g, cam)


def test_degenerate_flat_and_huge_gaussians_and_zero_opacity() -> None:
    g = random_gaussians(60, sh_degree=2, seed=9, extent=0.7)
    g.log_scales[:10, 2] = -30.0  # flat discs
    g.log_scales[10:15] = torch.tensor([1.5, 1.2, 1.0])  # huge: cover the whole image
    g.log_scales[15:20, :2] = -30.0  # needles
    g.opacity_logits[20:30] = -1e4  # opacity exactly zero after the sigmoid
    assert_forward_matches(g, make_camera(41, 27))


def test_sh_fixture_renders_without_nan() -> None:
    g = gsw.load_ply(require(FIXTURE, "shared data"))
    center = g.means.median(dim=0).values
    cams = gsw.orbit_cameras(center.tolist(), 3.0, 3, width=96, height=80)
    for cam in cams:
        out = rasterize(g, cam)
        assert torch.isfinite(out.image).all() and torch.isfinite(out.depth).all()
        assert int(out.visible.sum()) > 0


def test_deterministic_across_runs_and_thread_counts() -> None:
    g = frustum_scene(3000, make_camera(96, 80), sh_degree=1, seed=1)
    cam = make_camera(96, 80)
    params = [t.requires_grad_() for t in (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh)]

    def run() -> list[torch.Tensor]:
        for p in params:
            p.grad = None
        out = rasterize(g, cam)
        (out.image * torch.linspace(0, 1, 96)).sum().backward()
        return [out.image.detach()] + [p.grad.clone() for p in params]

    threads = torch.get_num_threads()
    first = run()
    try:
        torch.set_num_threads(1)
        single = run()
    finally:
        torch.set_num_threads(threads)
    again = run()
    for a, b, c in zip(first, single, again):
        assert torch.equal(a, b) and torch.equal(a, c)


def test_every_pixel_finishes_early_on_partial_tiles() -> None:
    # Opaque splats covering a 37x21 image (partial tiles in both axes): most pixels reach T_MIN before the last
    # splat, so the kernels' finished-pixel state and the per-block skips decide the results.
    from gsw.constants import T_MIN

    W, H = 37, 21
    cam = make_camera(W, H)
    g = random_gaussians(12, sh_degree=1, seed=21, extent=0.05, scale_range=(1.0, 1.5),
                         opacity_range=(0.995, 0.999))
    assert_forward_matches(g, cam)
    out = rasterize(g, cam)
    assert out.final_T.min().item() > 0 and out.final_T.max().item() < 1e3 * T_MIN
    assert (out.n_contrib < 12).float().mean().item() > 0.5  # most pixels stop before the last splat
    loss = _loss_fn(cam, 1, W, H, torch.float32)
    bg = torch.tensor([0.2, 0.1, 0.4])
    grads = []
    for use_ref in (False, True):
        inputs = [t.clone().requires_grad_() for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]
        loss(*inputs, bg, use_ref=use_ref).backward()
        grads.append([t.grad for t in inputs])
    for ours, ref in zip(*grads):
        assert ((ours - ref).norm() / ref.norm().clamp_min(1e-12)).item() <= 1e-4


def test_heavy_scene_matches_reference_and_is_deterministic() -> None:
    # Large, overlapping, partly opaque footprints: per-row chords, lane blocks that start mid-row and run
    # into the next row, finished blocks skipped, early termination; forward, backward and contribution.
    cam = Camera.from_fov(math.radians(60), 72, 56)
    g = heavy_scene(700, cam, seed=4, log_scale_mean=-2.8)
    # heavy_scene's Gaussians are isotropic (zero quaternion gradient): stretch them.
    stretch = 0.4 * torch.randn(g.log_scales.shape, generator=torch.Generator().manual_seed(5))
    g = Gaussians(g.means, g.log_scales + stretch, g.quats, g.opacity_logits, g.sh)
    assert_forward_matches(g, cam)
    weights = torch.rand(3, cam.height, cam.width, generator=torch.Generator().manual_seed(3))
    loss = _loss_fn(cam, 3, cam.width, cam.height, torch.float32)
    bg = torch.tensor([0.3, 0.2, 0.1])

    def run(use_ref: bool = False) -> list[torch.Tensor]:
        inputs = [t.clone().requires_grad_() for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]
        loss(*inputs, bg, use_ref=use_ref).backward()
        if use_ref:
            return [t.grad for t in inputs]
        out = rasterize(g, cam)
        with torch.no_grad():
            c = contribution(g, cam, weights)
        return [t.grad for t in inputs] + [out.image, c.values, c.hits.float(), c.max_weight]

    threads = torch.get_num_threads()
    first = run()
    try:
        torch.set_num_threads(1)
        single = run()
    finally:
        torch.set_num_threads(threads)
    for a, b, c in zip(first, single, run()):
        assert torch.equal(a, b) and torch.equal(a, c)
    names = ["means", "quats", "log_scales", "opacity_logits", "sh"]
    for name, ours, ref in zip(names, first, run(use_ref=True)):
        rel = (ours - ref).norm() / ref.norm().clamp_min(1e-12)
        assert rel.item() <= 1e-4, f"{name}: relative error {rel.item():.2e}"


# ----------------------------------------------------------------------------------------- backward


def _loss_fn(cam: Camera, sh_degree: int, W: int, H: int, dtype):
    gen = torch.Generator().manual_seed(11)
    wi = torch.randn(3, H, W, generator=gen, dtype=dtype)
    wa = torch.randn(1, H, W, generator=gen, dtype=dtype)
    wd = torch.randn(1, H, W, generator=gen, dtype=dtype)

    def loss(means, quats, log_scales, logits, sh, bg, *, use_ref=False):
        if use_ref:
            out = reference_rasterize(means, quats, log_scales, logits, sh, cam.viewmat, cam.fx,
                                      cam.fy, cam.cx, cam.cy, W, H, sh_degree, bg)
        else:
            out = rasterize(Gaussians(means, log_scales, quats, logits, sh), cam,
                            sh_degree=sh_degree, background=bg)
        return (out.image * wi).sum() + (out.alpha * wa).sum() + (out.depth * wd).sum()

    return loss


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_gradcheck_float64(sh_degree: int) -> None:
    W, H = 18, 14
    cam = make_camera(W, H, dtype=torch.float64, cx=8.3, cy=7.9)
    g = random_gaussians(5, sh_degree=sh_degree, seed=12, extent=0.4, scale_range=(0.08, 0.2),
                         opacity_range=(0.2, 0.7), dtype=torch.float64)
    bg = torch.tensor([0.1, 0.3, 0.2], dtype=torch.float64, requires_grad=True)
    loss = _loss_fn(cam, sh_degree, W, H, torch.float64)
    inputs = tuple(t.clone().requires_grad_() for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)) + (bg,)
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_float32_gradients_match_reference_autograd(sh_degree: int) -> None:
    W, H = 36, 28
    cam = make_camera(W, H)
    g = random_gaussians(40, sh_degree=sh_degree, seed=13 + sh_degree, extent=0.6,
                         scale_range=(0.03, 0.15))
    loss = _loss_fn(cam, sh_degree, W, H, torch.float32)
    bg = torch.tensor([0.2, 0.1, 0.4])
    grads = []
    for use_ref in (False, True):
        inputs = [t.clone().requires_grad_() for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]
        b = bg.clone().requires_grad_()
        loss(*inputs, b, use_ref=use_ref).backward()
        grads.append([t.grad for t in inputs] + [b.grad])
    names = ["means", "quats", "log_scales", "opacity_logits", "sh", "background"]
    for name, ours, ref in zip(names, *grads):
        rel = (ours - ref).norm() / ref.norm().clamp_min(1e-12)
        assert rel.item() <= 1e-4, f"{name}: relative error {rel.item():.2e}"


@pytest.mark.parametrize("outputs", [("image",), ("alpha",), ("depth",), ("alpha", "depth")])
def test_gradients_when_only_some_outputs_are_used(outputs: tuple[str, ...]) -> None:
    # Unused outputs reach the backward as None (no zero-filled cotangents): it must treat them as zero.
    W, H = 22, 17
    cam = make_camera(W, H, dtype=torch.float64)
    g = random_gaussians(12, sh_degree=1, seed=5, extent=0.5, scale_range=(0.05, 0.15), dtype=torch.float64)
    gen = torch.Generator().manual_seed(3)
    w = {name: torch.randn(c, H, W, generator=gen, dtype=torch.float64)
         for name, c in (("image", 3), ("alpha", 1), ("depth", 1))}
    bg = torch.tensor([0.2, 0.1, 0.4], dtype=torch.float64)
    grads = []
    for use_ref in (False, True):
        inputs = [t.clone().requires_grad_() for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]
        if use_ref:
            out = reference_rasterize(*inputs, cam.viewmat, cam.fx, cam.fy, cam.cx, cam.cy, W, H, 1, bg)
        else:
            out = rasterize(Gaussians(inputs[0], inputs[2], inputs[1], inputs[3], inputs[4]), cam, sh_degree=1,
                            background=bg)
        sum((getattr(out, name) * w[name]).sum() for name in outputs).backward()
        grads.append([torch.zeros_like(t) if t.grad is None else t.grad for t in inputs])  # unused -> None
    for ours, ref in zip(*grads):
        assert (ours - ref).norm() <= 1e-8 * ref.norm().clamp_min(1e-12), f"{outputs}: {ours} vs {ref}"
    assert any(t.abs().sum() > 0 for t in grads[0])  # the loss does reach the Gaussians


def test_screen_space_gradient_is_exposed() -> None:
    cam = make_camera()
    g = random_gaussians(50, sh_degree=0, seed=14, extent=0.6)
    g.means.requires_grad_()
    out = rasterize(g, cam)
    out.means2d.retain_grad()
    out.image.sum().backward()
    grad2d = out.means2d.grad
    assert grad2d is not None and grad2d.shape == (50, 2)
    assert grad2d[out.visible].abs().sum() > 0 and grad2d[~out.visible].abs().sum() == 0


# ----------------------------------------------------------------------------------------- contribution


@pytest.mark.parametrize("channels", [1, 3, 5])
def test_contribution_is_gradient_of_colour_override(channels: int) -> None:
    W, H = 45, 31
    cam = make_camera(W, H)
    g = random_gaussians(150, sh_degree=1, seed=15, extent=0.7)
    weights = torch.rand(channels, H, W, generator=torch.Generator().manual_seed(2))
    res = contribution(g, cam, weights)
    assert res.values.shape == (150, channels)
    for c in range(channels):
        colors = torch.zeros(150, 3, requires_grad=True)
        out = rasterize(g, cam, colors=colors)
        (out.image[0] * weights[c]).sum().backward()
        expected = colors.grad[:, 0]
        assert torch.allclose(res.values[:, c], expected, rtol=1e-5, atol=1e-6)


def test_contribution_weights_sum_to_alpha_and_match_reference() -> None:
    W, H = 40, 30
    cam = make_camera(W, H)
    g = random_gaussians(120, sh_degree=0, seed=16, extent=0.7)
    out = rasterize(g, cam)
    ones = contribution(g, cam, torch.ones(1, H, W))
    # Per pixel: weights of all contributors sum to alpha; summed over pixels here, and per
    # pixel with one-hot weight maps on a few pixels.
    assert torch.allclose(ones.values.sum(), out.alpha.sum(), rtol=1e-5)
    for (y, x) in [(0, 0), (15, 20), (29, 39), (7, 33)]:
        onehot = torch.zeros(1, H, W)
        onehot[0, y, x] = 1.0
        assert torch.allclose(contribution(g, cam, onehot).values.sum(), out.alpha[0, y, x], atol=1e-6)
    p = out.projection
    weights = torch.rand(2, H, W, generator=torch.Generator().manual_seed(3))
    V, hits, max_w = reference_contribution(p.means2d, p.conics, p.opacities, p.depths, p.radii, W, H, weights)
    ours = contribution(g, cam, weights)
    assert torch.allclose(ours.values, V, atol=1e-5, rtol=1e-5)
    assert torch.equal(ours.hits, hits)
    assert torch.allclose(ours.max_weight, max_w, atol=1e-6)


# ----------------------------------------------------------------------------------------- APIs and errors


def test_bad_inputs_name_the_argument() -> None:
    from gsw import _C

    g = random_gaussians(10, sh_degree=1, seed=18)
    cam = make_camera()
    with pytest.raises(RuntimeError, match="quats"):
        project(g.means, g.quats[:, :3].contiguous(), g.log_scales, g.opacity_logits, g.sh, cam, 1)
    with pytest.raises(RuntimeError, match="log_scales.*dtype"):
        project(g.means, g.quats, g.log_scales.double(), g.opacity_logits, g.sh, cam, 1)
    with pytest.raises(RuntimeError, match="sh_degree"):
        project(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, cam, 4)
    with pytest.raises(RuntimeError, match="sh"):
        project(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, cam, 2)  # needs 9 coeffs
    with pytest.raises(ValueError, match="sh_degree"):
        rasterize(g, cam, sh_degree=3)
    with pytest.raises(ValueError, match="weights"):
        contribution(g, cam, torch.ones(1, 5, 5))
    bad = g.clone()
    bad.opacity_logits[3] = float("nan")
    with pytest.raises(ValueError, match="opacity_logits: 1 of 10"):
        rasterize(bad, cam)
    with pytest.raises(ValueError, match="background"):
        rasterize(g, cam, background=(1.0, 0.0))
    with pytest.raises(RuntimeError, match="fx"):
        _C.project_forward(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, 1, cam.viewmat,
                           -1.0, 1.0, 0.0, 0.0, 10, 10)


def test_build_info_reports_backends() -> None:
    info = gsw.build_info()
    assert {"compiler", "openmp", "threads", "cuda", "version", "torch"} <= set(info)
    assert info["threads"] >= 1 and info["version"] == gsw.__version__


@pytest.mark.skipif(not sys.platform.startswith("linux") or shutil.which("readelf") is None
                    or not gsw.build_info()["compiler"].startswith("GNU"), reason="needs Linux, GCC and readelf")
def test_extension_uses_the_shared_libstdcxx() -> None:
    # A private static libstdc++ inside the module crashed torch's error formatting (see CMakeLists.txt).
    from gsw import _C

    dynamic = subprocess.run(["readelf", "-d", _C.__file__], capture_output=True, text=True, check=True).stdout
    assert "libstdc++.so" in dynamic


# ----------------------------------------------------------------------------------------- validation


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("field", ["means", "quats", "log_scales", "opacity_logits", "sh"])
def test_validation_names_each_non_finite_field(field: str, value: float) -> None:
    g = random_gaussians(12, sh_degree=2, seed=3)
    cam = make_camera()
    bad = g.clone()
    getattr(bad, field).view(12, -1)[5, -1] = value  # for sh: a coefficient above degree 1
    with pytest.raises(ValueError, match=f"{field}: 1 of 12 rows contain NaN/Inf"):
        rasterize(bad, cam)
    with pytest.raises(ValueError, match=field):
        rasterize(bad, cam, sh_degree=1)  # every stored value is checked, not only the active degree
    rasterize(bad, cam, validate=False)  # no check asked for: renders whatever comes out


def test_validation_checks_culled_gaussians_and_the_colour_override() -> None:
    g = random_gaussians(12, sh_degree=1, seed=4)
    cam = make_camera()
    behind = g.clone()
    behind.means[2] = cam.center - 2.0 * cam.R[2]  # behind the camera: culled
    behind.log_scales[2, 0] = float("nan")
    with pytest.raises(ValueError, match="log_scales: 1 of 12"):
        rasterize(behind, cam)
    colors = torch.rand(12, 3)
    colors[7, 1] = float("inf")
    with pytest.raises(ValueError, match="colors"):
        rasterize(g, cam, colors=colors)
    out = rasterize(g, cam)  # a clean model passes, and the flags are in the projection
    assert out.projection.nonfinite is not None and int(out.projection.nonfinite) == 0 and out.bins.nonfinite == 0


# ----------------------------------------------------------------------------------------- opacity-aware footprints


def test_footprint_radius_follows_the_opacity() -> None:
    from gsw import constants as K

    z, ls = 2.0, -2.0
    cam = make_camera(64, 64, dtype=torch.float64)
    ops = [0.002, 0.004, 0.01, 0.05, 0.2, 0.5, 0.99]
    n = len(ops)
    g = random_gaussians(n, sh_degree=0, seed=5, dtype=torch.float64)
    g.means = (cam.center.double() + z * cam.R[2].double()).expand(n, 3).contiguous()
    g.quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).expand(n, 4).contiguous()
    g.log_scales = torch.full((n, 3), ls, dtype=torch.float64)
    g.opacity_logits = torch.logit(torch.tensor(ops, dtype=torch.float64))
    radii = rasterize(g, cam).radii.tolist()
    # Isotropic on the optical axis: both eigenvalues are var, and disc = 0 < EIGEN_FLOOR.
    sigma = math.sqrt((cam.fx * math.exp(ls) / z) ** 2 + K.COV2D_DILATION + math.sqrt(K.EIGEN_FLOOR))
    for op, r in zip(ops, radii):
        skip = math.log(K.ALPHA_MIN / op) - K.SKIP_LOG_MARGIN
        expected = 0 if skip >= 0 else min(math.ceil(K.RADIUS_SIGMAS * sigma), math.ceil(math.sqrt(-2 * skip) * sigma) + 1)
        assert r == expected, (op, r, expected)
    assert radii[0] == 0 and radii[-1] == math.ceil(K.RADIUS_SIGMAS * sigma) and 0 < radii[2] < radii[-1]


def _blend_with_radii(proj: Projection, radii: torch.Tensor, cam: Camera, weights: torch.Tensor):
    """Blends `proj`'s splats with other footprint radii; returns the outputs, the gradients and the bins."""
    leaves = {k: getattr(proj, k).detach().clone().requires_grad_()
              for k in ("means2d", "conics", "depths", "colors", "opacities")}
    p = Projection(**leaves, radii=radii)
    bins = bin_gaussians(p, cam.width, cam.height)
    image, alpha, depth, final_T, _ = blend(p, cam.width, cam.height, torch.zeros(3, dtype=proj.means2d.dtype))
    ((image * weights).sum() + alpha.sum() + 0.1 * depth.sum()).backward()
    return [image, alpha, depth, final_T], {k: t.grad for k, t in leaves.items()}, bins


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_opacity_aware_footprints_change_no_pixel_and_no_gradient(dtype: torch.dtype) -> None:
    cam = Camera.from_fov(math.radians(60), 96, 64)
    g = heavy_scene(3000, cam, seed=2, log_scale_mean=-2.5, dtype=dtype)
    tight = project(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, cam, 3)
    # INRIA's 3-sigma footprints: opaque logits size them, the blended opacities stay the real ones.
    wide = project(g.means, g.quats, g.log_scales, torch.full_like(g.opacity_logits, 10.0), g.sh, cam, 3)
    assert bool((tight.radii <= wide.radii).all()) and int((tight.radii < wide.radii).sum()) > 100
    weights = torch.rand(3, cam.height, cam.width, generator=torch.Generator().manual_seed(0), dtype=dtype)
    outs_t, grads_t, bins_t = _blend_with_radii(tight, tight.radii, cam, weights)
    outs_w, grads_w, bins_w = _blend_with_radii(tight, wide.radii, cam, weights)
    assert bins_t.num_intersections <= bins_w.num_intersections
    for a, b in zip(outs_t, outs_w):
        assert torch.equal(a, b)
    for k in grads_t:
        torch.testing.assert_close(grads_t[k], grads_w[k], rtol=0, atol=1e-12 if dtype == torch.float64 else 1e-7)


# ----------------------------------------------------------------------------------------- ellipse tile assignment


def _blend_with_bins(proj: Projection, bins, cam: Camera, seed: int = 0):
    """Blends `proj` on given bins with the kernels: (image, alpha, depth, final_T, n_contrib) and the five
    cotangents (v_means2d, v_conics, v_colors, v_opacities, v_depths) of random output weights."""
    from gsw._ext import _C

    dt = proj.means2d.dtype
    gen = torch.Generator().manual_seed(seed)
    w = [torch.rand(k, cam.height, cam.width, generator=gen, dtype=torch.float64).to(dt) for k in (3, 1, 1)]
    s = [getattr(proj, k).detach().contiguous() for k in ("means2d", "conics", "colors", "opacities", "depths")]
    bg = torch.zeros(3, dtype=dt)
    out = _C.rasterize_forward(*s, bg, bins=bins, width=cam.width, height=cam.height)
    grads = _C.rasterize_backward(*s, bg, bins=bins, width=cam.width, height=cam.height, final_T=out[3],
                                  n_contrib=out[4], v_image=w[0], v_alpha=w[1], v_depth=w[2])
    return list(out[:4]), list(grads)


def _thin_faint_scene(n: int, cam: Camera, dtype: torch.dtype, seed: int) -> Gaussians:
    """Random splats, many of them needle-thin, rotated and faint: the hard cases of the ellipse test."""
    gen = torch.Generator().manual_seed(seed)
    g = random_gaussians(n, sh_degree=1, seed=seed, extent=0.8, dtype=dtype)
    ls = torch.empty(n, 3, dtype=torch.float64).uniform_(-5.0, -1.0, generator=gen)
    ls[: n // 2, 0] = -7.0  # needles
    g.log_scales = ls.to(dtype)
    g.quats = torch.randn(n, 4, generator=gen, dtype=torch.float64).to(dtype)
    g.opacity_logits = torch.logit(torch.empty(n, dtype=torch.float64).uniform_(0.0035, 0.999, generator=gen)).to(dtype)
    return g


def _tile_membership(bins, n: int) -> torch.Tensor:
    """[N, tiles] bool: Gaussian g is in tile t's list."""
    m = torch.zeros(n, bins.tiles_x * bins.tiles_y, dtype=torch.bool)
    counts = (bins.tile_offsets[1:] - bins.tile_offsets[:-1]).long()
    tiles = torch.repeat_interleave(torch.arange(counts.numel()), counts)
    m[bins.gauss_ids.long(), tiles] = True
    return m


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_ellipse_tiles_hold_every_visible_pixel_and_match_the_reference(dtype: torch.dtype) -> None:
    from gsw import constants as K
    from gsw.render import _ops
    from gsw.render._reference import reference_tile_rects, reference_tile_spans

    cam = make_camera(83, 61, dtype=dtype, distance=2.5)
    g = _thin_faint_scene(600, cam, dtype, seed=7)
    p = project(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, cam, 1)
    n, W, H = g.means.shape[0], cam.width, cam.height
    bins = bin_gaussians(p, W, H)
    rect_bins = _ops.bins(p.means2d, torch.zeros_like(p.conics), p.opacities, p.radii, p.depths, W, H)
    binned, in_rect = _tile_membership(bins, n), _tile_membership(rect_bins, n)
    # the reference's spans are the kernels' bins
    spans = reference_tile_spans(p.means2d, p.conics, p.opacities, p.radii, W, H)
    tx = torch.arange(bins.tiles_x)
    ref = ((spans[:, :, 0:1] <= tx) & (tx < spans[:, :, 1:2])).reshape(n, -1)
    assert torch.equal(ref, binned)
    # within the radius rectangles, and strictly fewer tiles
    rects = reference_tile_rects(p.means2d, p.radii, W, H)
    assert torch.equal(in_rect.sum(1), ((rects[:, 2] - rects[:, 0]) * (rects[:, 3] - rects[:, 1])).long())
    assert not (binned & ~in_rect).any() and bins.num_intersections < 0.8 * rect_bins.num_intersections
    # every pixel of the rectangle where alpha (as the kernels compute it) reaches ALPHA_MIN has the splat
    jj, ii = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    px, py = ii.flatten().to(dtype) + 0.5, jj.flatten().to(dtype) + 0.5
    tile = (jj.flatten() // K.TILE_SIZE) * bins.tiles_x + ii.flatten() // K.TILE_SIZE
    m2, con = p.means2d.detach(), p.conics.detach()
    dx, dy = m2[:, 0:1] - px, m2[:, 1:2] - py
    power = -0.5 * (con[:, 0:1] * dx * dx + con[:, 2:3] * dy * dy) - con[:, 1:2] * dx * dy
    alpha = p.opacities.detach()[:, None] * torch.exp(power.clamp(max=0))
    needed = (alpha >= K.ALPHA_MIN) & (power <= 0) & in_rect[:, tile]
    assert int(needed.sum()) > 1000
    assert bool(binned[:, tile][needed].all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("family", ["heavy", "thin_faint", "ply"])
def test_ellipse_binning_changes_no_pixel_and_no_gradient(family: str, dtype: torch.dtype) -> None:
    from gsw.render import _ops

    if family == "ply":
        g = gsw.load_ply(require(FIXTURE, "shared data")).to(dtype=dtype)
        center = g.means.median(dim=0).values
        cam = gsw.orbit_cameras(center.tolist(), 3.0, 3, width=128, height=96)[1]
    elif family == "heavy":
        cam = Camera.from_fov(math.radians(60), 96, 64)
        g = heavy_scene(3000, cam, seed=2, log_scale_mean=-2.5, dtype=dtype)
    else:
        cam = make_camera(96, 64, dtype=dtype, distance=2.5)
        g = _thin_faint_scene(800, cam, dtype, seed=3)
    p = project(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, cam, g.sh_degree)
    W, H = cam.width, cam.height
    ellipse = bin_gaussians(p, W, H)
    rect = _ops.bins(p.means2d, torch.zeros_like(p.conics), p.opacities, p.radii, p.depths, W, H)
    assert ellipse.num_intersections < rect.num_intersections
    outs_e, grads_e = _blend_with_bins(p, ellipse, cam)
    outs_r, grads_r = _blend_with_bins(p, rect, cam)
    assert float(outs_e[1].max()) > 0.5
    for a, b in zip(outs_e + grads_e, outs_r + grads_r):
        assert torch.equal(a, b)


def test_a_background_given_as_numbers_is_made_once_per_device_and_dtype() -> None:
    """Numbers (or None) become one cached tensor per value, dtype and device (no host-to-device copy per render on
    CUDA); a cached background made under inference mode still serves a render with gradients."""
    from gsw.render.rasterize import _background

    like = torch.zeros(2)
    a, b = _background((1, 0.5, 0), like), _background([1.0, 0.5, 0.0], like)
    assert a is b and torch.equal(a, torch.tensor([1.0, 0.5, 0.0]))
    assert _background(None, like) is _background((0, 0, 0), like)
    assert _background((1, 0.5, 0), like.double()).dtype == torch.float64
    with torch.inference_mode():
        _background((0.25, 0.25, 0.25), like)
    g = random_gaussians(20, seed=3)
    g.sh.requires_grad_()
    cam = Camera.look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.9, 12, 10)
    rasterize(g, cam, background=(0.25, 0.25, 0.25)).image.sum().backward()
    assert g.sh.grad is not None
    with pytest.raises(ValueError, match="3 numbers"):
        _background("white", like)


def _render_grads(g: Gaussians, cam: Camera, weights: torch.Tensor) -> list[torch.Tensor]:
    leaves = [t.detach().clone().requires_grad_() for t in (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh)]
    out = rasterize(Gaussians(*leaves), cam, background=(0.1, 0.2, 0.3))
    ((out.image * weights).sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
    return [t.grad for t in leaves]


@pytest.mark.parametrize("family", ["frustum", "heavy"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_chunked_blend_backward_gives_the_same_gradient_bits(monkeypatch, family: str, dtype: torch.dtype) -> None:
    """Records over the budget (GSW_BLEND_RECORDS_MIB) are made and reduced a chunk of tiles at a time: every
    gradient equals the one-pass backward's bit for bit, for budgets of single tiles up to a few chunks."""
    if family == "heavy":
        cam = Camera.from_fov(math.radians(60), 96, 64)
        g = heavy_scene(3000, cam, seed=4, log_scale_mean=-2.5, dtype=dtype)
    else:
        cam = make_camera(96, 64, dtype=dtype, distance=2.5)
        g = frustum_scene(2000, cam, seed=5, dtype=dtype)
    weights = torch.rand(3, cam.height, cam.width, generator=torch.Generator().manual_seed(1), dtype=dtype)
    monkeypatch.setenv("GSW_BLEND_RECORDS_MIB", "0")  # no limit: one pass
    one_pass = _render_grads(g, cam, weights)
    m = rasterize(g, cam).bins.num_intersections
    row_mib = 10 * torch.finfo(dtype).bits / 8 / 2**20
    for rows in (1, 200, m // 3):  # every tile alone (a tile over the budget is a chunk), small chunks, 3-4 chunks
        assert rows < m
        monkeypatch.setenv("GSW_BLEND_RECORDS_MIB", repr(rows * row_mib))
        for a, b in zip(_render_grads(g, cam, weights), one_pass):
            assert torch.equal(a, b), rows


def test_a_bad_records_budget_is_named(monkeypatch) -> None:
    cam = make_camera(32, 32)
    g = random_gaussians(50, seed=0)
    monkeypatch.setenv("GSW_BLEND_RECORDS_MIB", "lots")
    with pytest.raises(RuntimeError, match="GSW_BLEND_RECORDS_MIB"):
        _render_grads(g, cam, torch.ones(3, 32, 32))
