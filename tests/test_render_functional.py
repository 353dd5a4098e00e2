"""gsw.rasterization, the gsplat 1.5.3 drop-in (gsw/render/functional.py)."""

from __future__ import annotations

import inspect
import math

import pytest
import torch

import gsw
from gsw.camera import Camera
from gsw.gaussians import Gaussians
from gsw.render.functional import rasterization
from gsw.render.rasterize import rasterize
from gsw.scenes import heavy_scene, random_gaussians

#: Every keyword of gsplat 1.5.3's ``rasterization`` (its signature, in order).
GSPLAT_1_5_3_PARAMS = (
    "means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "width", "height", "near_plane", "far_plane",
    "radius_clip", "eps2d", "sh_degree", "packed", "tile_size", "backgrounds", "render_mode", "sparse_grad", "absgrad",
    "rasterize_mode", "channel_chunk", "distributed", "camera_model", "segmented", "covars", "with_ut",
    "with_eval3d", "radial_coeffs", "tangential_coeffs", "thin_prism_coeffs", "ftheta_coeffs", "rolling_shutter",
    "viewmats_rs")


def make_camera(width: int = 32, height: int = 24, *, distance: float = 3.0) -> Camera:
    return Camera.look_at((0.3, -distance, 0.4), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.9, width, height)


def two_views(width: int = 32, height: int = 24) -> tuple[list[Camera], torch.Tensor, torch.Tensor]:
    cams = [make_camera(width, height), make_camera(width, height, distance=4.0)]
    return cams, torch.stack([c.viewmat.float() for c in cams]), torch.stack([c.K.float() for c in cams])


def args_of(g: Gaussians) -> tuple[torch.Tensor, ...]:
    return g.means, g.quats, g.scales, g.opacities, g.sh


def test_signature_takes_every_gsplat_keyword_with_gsplat_defaults() -> None:
    params = inspect.signature(rasterization).parameters
    assert tuple(params) == GSPLAT_1_5_3_PARAMS
    for name, value in (("near_plane", 0.01), ("far_plane", 1e10), ("radius_clip", 0.0), ("eps2d", 0.3),
                        ("packed", True), ("tile_size", 16), ("render_mode", "RGB"), ("rasterize_mode", "classic"),
                        ("camera_model", "pinhole")):
        assert params[name].default == value, name
    gsplat = pytest.importorskip("gsplat")
    assert tuple(inspect.signature(gsplat.rasterization).parameters) == GSPLAT_1_5_3_PARAMS


def test_matches_rasterize() -> None:
    cams, viewmats, Ks = two_views()
    g = random_gaussians(60, sh_degree=2, seed=17, extent=0.6)
    colors, alphas, meta = rasterization(*args_of(g), viewmats, Ks, 32, 24, sh_degree=2, packed=False)
    assert colors.shape == (2, 24, 32, 3) and alphas.shape == (2, 24, 32, 1)
    assert meta["radii"].shape == (2, 60, 2) and meta["radii"].dtype == torch.int32
    assert meta["means2d"].shape == (2, 60, 2) and meta["gaussian_ids"] is None and meta["n_cameras"] == 2
    for i, cam in enumerate(cams):
        out = rasterize(g, cam)
        assert torch.allclose(colors[i], out.image.permute(1, 2, 0), atol=1e-5)
        assert torch.allclose(alphas[i], out.alpha.permute(1, 2, 0), atol=1e-5)
        assert torch.equal(meta["radii"][i, :, 0], out.radii) and torch.equal(meta["radii"][i, :, 1], out.radii)
        assert torch.allclose(meta["depths"][i], out.projection.depths, atol=1e-5)
    # Direct colours, and gradients reach the activated parameters.
    opac = g.opacities.clone().requires_grad_()
    rgb = torch.rand(60, 3, requires_grad=True)
    colors, _, _ = rasterization(g.means, g.quats, g.scales, opac, rgb, viewmats, Ks, 32, 24)
    colors.sum().backward()
    assert opac.grad.abs().sum() > 0 and rgb.grad.abs().sum() > 0


def test_sizes_footprints_from_the_given_opacities() -> None:
    cam = Camera.from_fov(math.radians(60), 64, 48)
    g = heavy_scene(500, cam, seed=6, log_scale_mean=-2.5)
    _, _, meta = rasterization(*args_of(g), cam.viewmat[None], cam.K[None], cam.width, cam.height, sh_degree=3,
                               packed=False)
    assert torch.equal(meta["radii"][0, :, 0], rasterize(g, cam).radii)


def test_meta_means2d_carries_the_screen_space_gradient() -> None:
    cams, viewmats, Ks = two_views()
    g = random_gaussians(80, sh_degree=1, seed=3, extent=0.6)
    g = Gaussians(**{k: v.detach().clone().requires_grad_() for k, v in g.parameters().items()})
    target = torch.rand(2, 24, 32, 3, generator=torch.Generator().manual_seed(0))
    colors, _, meta = rasterization(*args_of(g), viewmats, Ks, 32, 24, sh_degree=1, packed=False)
    meta["means2d"].retain_grad()
    ((colors - target) ** 2).sum().backward()
    grad = meta["means2d"].grad
    assert grad is not None and grad.shape == (2, 80, 2) and grad.abs().sum() > 0
    for i, cam in enumerate(cams):  # the same gradient as rasterize's projection receives for that view's loss
        out = rasterize(g, cam)
        out.means2d.retain_grad()
        ((out.image.permute(1, 2, 0) - target[i]) ** 2).sum().backward()
        torch.testing.assert_close(grad[i], out.means2d.grad, rtol=1e-4, atol=1e-5)
    # packed: [nnz, 2] entries of the visible (camera, Gaussian) pairs, the same gradients
    colors_p, _, meta_p = rasterization(*args_of(g), viewmats, Ks, 32, 24, sh_degree=1, packed=True)
    meta_p["means2d"].retain_grad()
    ((colors_p - target) ** 2).sum().backward()
    cam_ids, g_ids = meta_p["camera_ids"], meta_p["gaussian_ids"]
    assert torch.equal(colors_p, colors) and meta_p["means2d"].shape == (len(g_ids), 2)
    assert torch.equal(meta_p["radii"], meta["radii"][cam_ids, g_ids]) and bool((meta_p["radii"] > 0).all())
    assert int((meta["radii"][..., 0] > 0).sum()) == len(g_ids)
    torch.testing.assert_close(meta_p["means2d"].grad, grad[cam_ids, g_ids])


def test_render_modes_and_backgrounds() -> None:
    cams, viewmats, Ks = two_views()
    g = random_gaussians(60, sh_degree=0, seed=5, extent=0.6)
    bg = torch.tensor([[0.2, 0.5, 1.0], [1.0, 1.0, 1.0]])
    rgb, alpha, _ = rasterization(*args_of(g), viewmats, Ks, 32, 24, sh_degree=0, backgrounds=bg)
    modes = {m: rasterization(*args_of(g), viewmats, Ks, 32, 24, sh_degree=0, backgrounds=bg, render_mode=m)[0]
             for m in ("D", "ED", "RGB+D", "RGB+ED")}
    for i, cam in enumerate(cams):
        out = rasterize(g, cam, background=bg[i])
        depth = out.depth.permute(1, 2, 0)
        assert torch.allclose(rgb[i], out.image.permute(1, 2, 0), atol=1e-5)
        assert torch.allclose(modes["D"][i], depth, atol=1e-5)
        assert torch.allclose(modes["ED"][i], depth / alpha[i].clamp(min=1e-10), atol=1e-4)
    assert modes["RGB+D"].shape == (2, 24, 32, 4)
    assert torch.equal(modes["RGB+D"][..., :3], rgb) and torch.equal(modes["RGB+D"][..., 3:], modes["D"])
    assert torch.equal(modes["RGB+ED"][..., 3:], modes["ED"])
    with pytest.raises(ValueError, match="render_mode"):
        rasterization(*args_of(g), viewmats, Ks, 32, 24, sh_degree=0, render_mode="RGBD")


def test_colours_of_any_channel_count() -> None:
    _, viewmats, Ks = two_views()
    g = random_gaussians(60, sh_degree=0, seed=6, extent=0.6)
    feats = torch.rand(60, 5, generator=torch.Generator().manual_seed(1))
    bg = torch.rand(2, 5, generator=torch.Generator().manual_seed(2))
    out, _, _ = rasterization(g.means, g.quats, g.scales, g.opacities, feats, viewmats, Ks, 32, 24, backgrounds=bg)
    first, _, _ = rasterization(g.means, g.quats, g.scales, g.opacities, feats[:, :3], viewmats, Ks, 32, 24,
                                backgrounds=bg[:, :3])
    rest = torch.cat([feats[:, 3:], torch.zeros(60, 1)], dim=1)
    last, _, _ = rasterization(g.means, g.quats, g.scales, g.opacities, rest, viewmats, Ks, 32, 24,
                               backgrounds=torch.cat([bg[:, 3:], torch.zeros(2, 1)], dim=1))
    assert out.shape == (2, 24, 32, 5)
    assert torch.equal(out[..., :3], first) and torch.equal(out[..., 3:], last[..., :2])
    per_camera = feats[None].repeat(2, 1, 1)  # [C, N, D] colours
    assert torch.equal(rasterization(g.means, g.quats, g.scales, g.opacities, per_camera, viewmats, Ks, 32, 24,
                                     backgrounds=bg)[0], out)


def test_near_and_far_planes() -> None:
    cam = make_camera(32, 24)
    g = random_gaussians(80, sh_degree=1, seed=7, extent=0.6)  # all depths well beyond 0.35
    ref, _, meta_ref = rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=1, packed=False,
                                     near_plane=0.2)
    for near in (0.01, 0.35):  # rendered scaled about the camera: the same image, radii and depths
        img, _, meta = rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=1, packed=False,
                                     near_plane=near)
        assert torch.allclose(img, ref, atol=1e-5) and torch.equal(meta["radii"], meta_ref["radii"])
        assert torch.allclose(meta["depths"], meta_ref["depths"], rtol=1e-5)
    depths = meta_ref["depths"][0]
    far = float(depths[meta_ref["radii"][0, :, 0] > 0].median())
    _, _, meta = rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=1, packed=False,
                               far_plane=far)
    visible = meta["radii"][0, :, 0] > 0
    assert bool((depths[visible] < far).all()) and int(visible.sum()) < int((meta_ref["radii"][0, :, 0] > 0).sum())
    # A Gaussian 0.1 in front of the camera: culled by a 0.2 near plane, drawn with gsplat's default 0.01.
    R, t = cam.viewmat[:3, :3].float(), cam.viewmat[:3, 3].float()
    close = Gaussians(means=(R.T @ (torch.tensor([0.0, 0.0, 0.1]) - t))[None], log_scales=torch.full((1, 3), -5.0),
                      quats=torch.tensor([[1.0, 0, 0, 0]]), opacity_logits=torch.tensor([2.0]),
                      sh=torch.ones(1, 1, 3))
    for near, drawn in ((0.01, True), (0.2, False)):
        _, alpha, meta = rasterization(*args_of(close), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=0,
                                       packed=False, near_plane=near)
        assert bool(meta["radii"][0, 0, 0] > 0) == drawn and bool(alpha.sum() > 0) == drawn


def test_radius_clip() -> None:
    cam = make_camera(32, 24)
    g = random_gaussians(80, sh_degree=0, seed=8, extent=0.6)
    _, _, meta = rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=0, packed=False)
    r = meta["radii"][0, :, 0]
    clip = float(r[r > 0].float().median())
    _, _, clipped = rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=0, packed=False,
                                  radius_clip=clip)
    assert torch.equal(clipped["radii"][0, :, 0], torch.where(r <= clip, 0, r))


def test_antialiased_mode_scales_opacities_by_the_compensation() -> None:
    cam = make_camera(32, 24)
    g = random_gaussians(80, sh_degree=0, seed=9, extent=0.6)
    classic = rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=0, packed=False)
    img, _, meta = rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=0, packed=False,
                                 rasterize_mode="antialiased")
    vis = meta["radii"][0, :, 0] > 0
    a, b, c = classic[2]["conics"][0][vis].double().unbind(-1)
    dilated = torch.linalg.inv(torch.stack([torch.stack([a, b], -1), torch.stack([b, c], -1)], -2))
    cov = dilated - 0.3 * torch.eye(2, dtype=torch.float64)
    comp = torch.sqrt((torch.linalg.det(cov) / torch.linalg.det(dilated)).clamp_min(0))
    assert bool((comp < 1).all())
    torch.testing.assert_close(meta["opacities"][0][vis].double(), g.opacities[vis].double() * comp, rtol=1e-4,
                               atol=1e-6)
    # = the classic render with those opacities (footprints sized from the uncompensated ones)
    compensated = meta["opacities"][0].detach()
    ref = rasterization(g.means, g.quats, g.scales, compensated, g.sh, cam.viewmat[None], cam.K[None], 32, 24,
                        sh_degree=0)[0]
    assert torch.allclose(img, ref, atol=1e-5) and not torch.allclose(img, classic[0], atol=1e-3)


@pytest.mark.parametrize("option", [
    {"absgrad": True}, {"sparse_grad": True}, {"distributed": True}, {"camera_model": "fisheye"}, {"eps2d": 0.1},
    {"with_ut": True}, {"with_eval3d": True}, {"covars": torch.eye(3).repeat(10, 1, 1)},
    {"radial_coeffs": torch.zeros(1, 6)}, {"rolling_shutter": "ROLLING_TOP_TO_BOTTOM"},
    {"viewmats_rs": torch.eye(4)[None]}, {"sh_degree": 4}])
def test_unsupported_options_raise_not_implemented_naming_them(option: dict) -> None:
    g = random_gaussians(10, sh_degree=3, seed=10)
    cam = make_camera()
    colors = torch.zeros(10, 25, 3) if option.get("sh_degree") == 4 else g.sh
    kwargs = {"sh_degree": 3, **option}
    name = next(iter(option))
    with pytest.raises(NotImplementedError, match=name):
        rasterization(g.means, g.quats, g.scales, g.opacities, colors, cam.viewmat[None], cam.K[None], 32, 24,
                      **kwargs)


def test_accepted_scheduling_options_and_bad_inputs() -> None:
    g = random_gaussians(10, sh_degree=0, seed=11)
    cam = make_camera()
    base = rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=0)[0]
    same = rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=0, tile_size=8,
                         channel_chunk=1, segmented=True, packed=False)[0]
    assert torch.equal(base, same)
    with pytest.raises(NotImplementedError, match="means"):
        rasterization(g.means[None], g.quats[None], g.scales[None], g.opacities[None], g.sh[None],
                      cam.viewmat[None, None], cam.K[None, None], 32, 24, sh_degree=0)
    with pytest.raises(NotImplementedError, match="viewmats"):
        rasterization(*args_of(g), cam.viewmat[None].clone().requires_grad_(), cam.K[None], 32, 24, sh_degree=0)
    with pytest.raises(ValueError, match="colors"):
        rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=1)  # 1 coefficient, needs 4
    with pytest.raises(ValueError, match="backgrounds"):
        rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=0, backgrounds=torch.ones(3))
    with pytest.raises(ValueError, match="near_plane"):
        rasterization(*args_of(g), cam.viewmat[None], cam.K[None], 32, 24, sh_degree=0, near_plane=0.0)


def test_gsplat_default_strategy_densifies_and_prunes_with_gsw_rasterization() -> None:
    strategy_mod = pytest.importorskip("gsplat.strategy")
    cam = make_camera(32, 24)
    scene = random_gaussians(150, sh_degree=1, seed=12, extent=0.6)
    with torch.no_grad():
        target = rasterize(scene, cam, background=torch.ones(3)).image.permute(1, 2, 0)[None]
    g = random_gaussians(100, sh_degree=1, seed=13, extent=0.6)
    logits = g.opacity_logits.clone()
    logits[:10] = -10.0  # below DefaultStrategy's prune_opa: removed at the first refinement
    params = torch.nn.ParameterDict({"means": g.means, "scales": g.log_scales, "quats": g.quats,
                                     "opacities": logits, "sh0": g.sh[:, :1], "shN": g.sh[:, 1:]})
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.detach().clone()) for k, v in params.items()})
    optimizers = {k: torch.optim.Adam([{"params": p, "lr": 1e-3, "name": k}], eps=1e-15) for k, p in params.items()}
    strategy = strategy_mod.DefaultStrategy(refine_start_iter=4, refine_stop_iter=20, refine_every=5,
                                            grow_grad2d=1e-7, reset_every=1000)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    counts = []
    for step in range(20):
        colors = torch.cat([params["sh0"], params["shN"]], dim=1)
        img, _, info = gsw.rasterization(params["means"], params["quats"], torch.exp(params["scales"]),
                                         torch.sigmoid(params["opacities"]), colors, cam.viewmat[None].float(),
                                         cam.K[None].float(), 32, 24, sh_degree=1, backgrounds=torch.ones(1, 3),
                                         packed=False)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        (img - target).abs().mean().backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        counts.append(len(params["means"]))
    assert counts[0] == 100 and max(counts) > 100  # grown (duplicated / split)
    assert bool((torch.sigmoid(params["opacities"]) > strategy.prune_opa).all())  # the faint ones pruned
    assert all(len(p) == counts[-1] for p in params.values())
