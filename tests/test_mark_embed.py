"""gsw.embed / extract / verify on the built-in scene (small and fast)."""

from __future__ import annotations

import pytest
import torch

from gsw.mark import EmbedConfig, embed, extract, verify
from gsw.mark.embed import paper_config
from gsw.mark.loss import LossWeights
from gsw.scenes import default_scene


EPOCHS = 20


@pytest.fixture(scope="module")
def scene():
    # 96x96: the decoder reads the LL2 subband (24x24 here); at 64x64 (16x16) 32 bits plateau near 93 %
    return default_scene(width=96, height=96, n_cameras=6, detail=0.5)


@pytest.fixture(scope="module")
def result(scene):
    bg = tuple(float(v) for v in scene.background)
    # the paper's recipe: on a 96-px scene of 6 views it reads the embedding views after 120 steps; the default
    # (a sampled viewpoint every step) needs more steps than a fast test affords
    cfg = paper_config(epochs=EPOCHS, lpips_net=None, weights={"lpips": 0.0}, background=bg)
    before = scene.gaussians.clone()
    res = embed(scene.gaussians, scene.cameras, message="0xc0ffee42", num_bits=32, config=cfg,
                progress=False)
    # the input model is never modified
    for name, t in before.parameters().items():
        assert torch.equal(t, scene.gaussians.parameters()[name]), name
    return res


def test_paper_config_pins_the_papers_image_term_and_takes_weight_overrides() -> None:
    """The library default's image term is the squared error; the paper's recipe pins L1. A mapping for ``weights``
    replaces single fields of the recipe's weights, a :class:`LossWeights` replaces them all."""
    default, paper = EmbedConfig().weights, paper_config().weights
    assert (default.l1, default.mse, paper.l1, paper.mse) == (0.0, 35.0, 1.0, 0.0)
    assert paper_config(weights={"lpips": 0.0}).weights == LossWeights(l1=1.0, mse=0.0, lpips=0.0)
    assert paper_config(weights=LossWeights(message=0.4)).weights == LossWeights(message=0.4)
    assert paper_config(epochs=3, fgd=False).epochs == 3 and not paper_config(fgd=False).fgd
    with pytest.raises(ValueError, match="unknown LossWeights fields"):
        paper_config(weights={"l2": 1.0})
    with pytest.raises(ValueError, match="unknown EmbedConfig fields"):
        paper_config(epoch=3)


def test_embed_result_structure(scene, result) -> None:
    assert result.message_hex == "c0ffee42" and result.message.shape == (32,)
    assert result.prune is not None and result.split is not None
    n_in = len(scene.gaussians)
    assert len(result.gaussians) == n_in - result.prune.num_removed + result.split.num_split
    assert len(result.bit_accuracy) == len(result.psnr) == len(scene.cameras)
    assert len(result.history) == EPOCHS * len(scene.cameras)
    assert {"renders", "fgd", "finetune", "evaluate", "total"} <= set(result.timings)
    # positions are frozen by default; FGD children aside, kept Gaussians did not move
    assert not result.gaussians.means.requires_grad


def test_embedding_raises_bit_accuracy(scene, result) -> None:
    bg = tuple(float(v) for v in scene.background)
    before = verify((scene.gaussians, scene.cameras), result.message, background=bg)
    after = verify((result.gaussians, scene.cameras), result.message, background=bg)
    assert sum(after.bit_accuracy) / 6 >= 0.95  # the end-to-end target on a tiny CPU scene
    assert sum(after.bit_accuracy) / 6 >= sum(before.bit_accuracy) / 6 + 0.3
    assert after.p_value < before.p_value
    assert min(result.psnr) > 28.0


def test_extract_and_verify_images(scene, result) -> None:
    from gsw.render.rasterize import rasterize

    bg = tuple(float(v) for v in scene.background)
    imgs = [rasterize(result.gaussians, c, background=bg).image.clamp(0, 1) for c in scene.cameras]
    ext = extract(imgs)
    assert ext.bits.shape == (6, 32) and ext.logits.shape == (6, 32)
    v = verify(imgs, result.message_hex)
    assert v.matches == [int((b == result.message).sum()) for b in ext.bits]
    assert v.bit_accuracy == [m / 32 for m in v.matches]
    with pytest.raises(ValueError, match="RGB"):
        extract(torch.rand(2, 64, 64))
    with pytest.raises(ValueError, match="num_bits"):
        verify(imgs, "key:secret")


def test_bad_inputs(scene) -> None:
    with pytest.raises(ValueError, match="camera"):
        embed(scene.gaussians, [], progress=False)
    with pytest.raises(ValueError, match="expected 32"):
        embed(scene.gaussians, scene.cameras, message=[0, 1, 1], progress=False)
    bad = scene.gaussians.clone()
    bad.means[0, 0] = float("nan")
    with pytest.raises(ValueError, match="means"):
        embed(bad, scene.cameras, progress=False)


def test_bad_attack_settings(scene) -> None:
    with pytest.raises(ValueError, match="model_attacks"):
        embed(scene.gaussians, scene.cameras, config=EmbedConfig(model_attacks=1.5), progress=False)
    with pytest.raises(ValueError, match="attacks"):
        embed(scene.gaussians, scene.cameras, config=EmbedConfig(attacks=-0.1), progress=False)
    with pytest.raises(ValueError, match="model_noise"):
        embed(scene.gaussians, scene.cameras, config=EmbedConfig(model_noise=-1.0), progress=False)


def test_train_time_model_attack_is_differentiable_and_spares_positions(scene) -> None:
    import random

    from gsw.attacks.distort import distort

    g = scene.gaussians.clone()
    sh = g.sh.clone().requires_grad_()
    g = type(g)(g.means, g.log_scales, g.quats, g.opacity_logits, sh)
    seen = set()
    for seed in range(8):
        _, out = distort(g, ("noise", "sh0"), random.Random(seed), torch.Generator().manual_seed(seed), 0.1)
        assert torch.equal(out.means, g.means)
        if torch.equal(out.log_scales, g.log_scales):  # the SH-degree-0 variant
            assert (out.sh[:, 1:] == 0).all() and torch.equal(out.sh[:, :1], g.sh[:, :1])
            seen.add("sh0")
        else:  # parameter noise of std 0.1 on everything but the positions
            for name in ("log_scales", "quats", "opacity_logits", "sh"):
                assert abs(float((getattr(out, name) - getattr(g, name)).std()) - 0.1) < 0.01, name
            seen.add("noise")
        (grad,) = torch.autograd.grad(out.sh.sum(), sh)
        assert grad[:, :1].eq(1).all()  # the clean colour receives the gradient through the attack
    assert seen == {"sh0", "noise"}


def test_embed_with_train_time_model_and_image_attacks_runs(scene) -> None:
    bg = tuple(float(v) for v in scene.background)
    cfg = EmbedConfig(epochs=1, lpips_net=None, weights=LossWeights(lpips=0.0), background=bg, fgd=False,
                      attacks=1.0, model_attacks=1.0)
    res = embed(scene.gaussians, scene.cameras, num_bits=32, config=cfg, progress=False)
    assert len(res.history) == len(scene.cameras)
    assert all(torch.isfinite(torch.tensor(h["loss"])) for h in res.history)


def _quick(scene, **kw) -> EmbedConfig:
    bg = tuple(float(v) for v in scene.background)
    return EmbedConfig(**{"epochs": 1, "lpips_net": None, "weights": LossWeights(lpips=0.0), "background": bg,
                          "fgd": False, **kw})


def test_embed_without_cameras_samples_views_around_the_content(scene) -> None:
    from gsw.mark.views import content_bounds

    cfg = _quick(scene, sampled_views=3, sampled_view_size=64, fgd=True)
    res = embed(scene.gaussians, None, num_bits=32, config=cfg, progress=False)
    assert len(res.cameras) == 3 and len(res.history) == 3 and len(res.bit_accuracy) == 3
    centre, radius = content_bounds(scene.gaussians)
    for cam in res.cameras:
        assert (cam.width, cam.height) == (64, 64) and cam.name.startswith("sampled_")
        uv, depth = cam.project(centre[None].float())
        assert depth[0] > 0 and 0 <= uv[0, 0] <= 64 and 0 <= uv[0, 1] <= 64
        assert float((cam.center.double() - centre).norm()) > radius
    again = embed(scene.gaussians, None, num_bits=32, config=cfg, progress=False)
    assert all(torch.equal(a.viewmat, b.viewmat) for a, b in zip(res.cameras, again.cameras))
    with pytest.raises(ValueError, match="at least one camera"):
        embed(scene.gaussians, [], config=cfg, progress=False)


def test_embed_with_novel_views_render_scales_and_export_distortions(scene) -> None:
    cfg = _quick(scene, novel_views=0.5, render_scales=(0.5, 2.0), max_render_side=128, model_attacks=1.0,
                 model_attack_kinds=("splat", "spz", "8bit", "sh0", "noise"), attacks=0.5, attack_ranges="matched")
    res = embed(scene.gaussians, scene.cameras, num_bits=32, config=cfg, progress=False)
    assert len(res.history) == len(scene.cameras) and res.cameras == list(scene.cameras)
    assert all(torch.isfinite(torch.tensor(h["loss"])) for h in res.history)
    for bad, match in (({"novel_views": 1.5}, "novel_views"), ({"render_scales": (2.0, 1.0)}, "render_scales"),
                       ({"attack_ranges": "strong"}, "attack_ranges"), ({"model_attack_kinds": ("blur",)}, "kinds"),
                       ({"split_opacity": "mass"}, "split_opacity")):
        with pytest.raises(ValueError, match=match):
            embed(scene.gaussians, scene.cameras, config=_quick(scene, **bad), progress=False)


def test_step_views_are_sampled_rescaled_and_seeded(scene) -> None:
    from gsw.mark.embed import _Views

    originals = [torch.zeros(3, c.height, c.width) for c in scene.cameras]
    cfg = _quick(scene, novel_views=0.5, render_scales=(0.5, 2.0), max_render_side=128)

    def steps():
        views = _Views(scene.gaussians, scene.cameras, originals, cfg)
        return [views.step(i % len(scene.cameras)) for i in range(12)]

    a, b = steps(), steps()
    assert any(c.name.startswith("sampled_") for c, _ in a) and any(not c.name.startswith("sampled_") for c, _ in a)
    assert len({c.width for c, _ in a}) > 3 and max(max(c.width, c.height) for c, _ in a) <= 128
    for (ca, ta), (cb, tb) in zip(a, b):
        assert torch.equal(ca.viewmat, cb.viewmat) and ca.width == cb.width and torch.equal(ta, tb)
        assert ta.shape == (3, ca.height, ca.width) and float(ta.sum()) > 0  # a fresh original render


def test_step_views_from_a_bank_are_its_viewpoints_rendered_once(scene, monkeypatch) -> None:
    from gsw.mark.embed import ViewBank, _Views, check_config

    originals = [torch.zeros(3, c.height, c.width) for c in scene.cameras]
    cfg = _quick(scene, novel_views=1.0, view_bank=2, max_render_side=128)
    views = _Views(scene.gaussians, scene.cameras, originals, cfg)
    assert len(views.bank) == 2
    renders = []
    real = ViewBank.render_camera
    monkeypatch.setattr(ViewBank, "render_camera", lambda self, cam: renders.append(cam) or real(self, cam))
    steps = [views.step(0) for _ in range(8)]
    assert all(any(cam is b for b in views.bank.cameras) for cam, _ in steps)
    assert len(renders) == len({id(cam) for cam, _ in steps}) == 2  # each bank viewpoint rendered once
    same = [t for cam, t in steps if cam is steps[0][0]]
    assert all(t is same[0] for t in same) and float(same[0].sum()) > 0
    with pytest.raises(ValueError, match="view_bank must be an integer >= 0"):
        check_config(_quick(scene, view_bank=-2), scene.cameras)


def test_extract_reads_images_of_different_sizes_one_by_one() -> None:
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(3, 64, 64, generator=g), torch.rand(3, 96, 80, generator=g)
    both = extract([a, b], num_bits=32)
    assert both.bits.shape == (2, 32)
    assert torch.allclose(both.logits[0], extract(a).logits[0]) and torch.allclose(both.logits[1], extract(b).logits[0])
    with pytest.raises(ValueError, match="image 1: expected a \\[3,H,W\\]"):
        extract([a, torch.rand(4, 64, 64)])
    with pytest.raises(ValueError, match="no images"):
        extract([])


def test_freeze_keeps_the_frozen_groups_and_is_deterministic(scene) -> None:
    cfg = _quick(scene, freeze=("f_rest", "scaling"), novel_views=0.5, max_render_side=128)
    a = embed(scene.gaussians, scene.cameras, message="0xc0ffee42", num_bits=32, config=cfg, progress=False)
    g = scene.gaussians
    assert torch.equal(a.gaussians.sh[:, 1:], g.sh[:, 1:]) and torch.equal(a.gaussians.log_scales, g.log_scales)
    assert not torch.equal(a.gaussians.sh[:, :1], g.sh[:, :1])  # the others still learn
    assert not torch.equal(a.gaussians.opacity_logits, g.opacity_logits)
    b = embed(scene.gaussians, scene.cameras, message="0xc0ffee42", num_bits=32, config=cfg, progress=False)
    for name, t in a.gaussians.parameters().items():
        assert torch.equal(t, b.gaussians.parameters()[name]), name
    for bad in (("f_rst",), ("f_dc", "f_rest", "opacity", "scaling", "rotation")):
        with pytest.raises(ValueError, match="freeze"):
            embed(scene.gaussians, scene.cameras, config=_quick(scene, freeze=bad), progress=False)


def test_psnr_target_steers_the_message_weight(scene) -> None:
    # a target above what the fine-tune reaches lowers the weight; one far below raises it
    for target, sign in ((150.0, -1), (1.0, 1)):
        res = embed(scene.gaussians, scene.cameras, message="0xc0ffee42", num_bits=32,
                    config=_quick(scene, epochs=3, psnr_target=target), progress=False)
        weights = [h["message_weight"] for h in res.history]
        assert weights[0] == pytest.approx(0.15) and (weights[-1] - 0.15) * sign > 0
        assert all(h["psnr"] > 0 for h in res.history)
    fixed = embed(scene.gaussians, scene.cameras, message="0xc0ffee42", num_bits=32, config=_quick(scene),
                  progress=False)
    assert {h["message_weight"] for h in fixed.history} == {0.15}
    for bad in ({"psnr_target": float("nan")}, {"psnr_target": -3.0}, {"psnr_weight_range": 0.5}):
        with pytest.raises(ValueError, match="psnr"):
            embed(scene.gaussians, scene.cameras, config=_quick(scene, **bad), progress=False)

