"""Tests for :mod:`gsw.attacks.model` (model attacks on Gaussians, the fine-tuning attack)."""

from __future__ import annotations

import math

import pytest
from helpers import random_model
import torch

from gsw import attacks as A
from gsw.gaussians import Gaussians


def snapshot(g: Gaussians) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in g.parameters().items()}


def assert_untouched(g: Gaussians, snap: dict[str, torch.Tensor]) -> None:
    for k, v in g.parameters().items():
        assert torch.equal(v, snap[k]), k


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


def test_finetune_rejects_bad_arguments(tiny_scene):
    with pytest.raises(ValueError, match="steps"):
        A.finetune(tiny_scene.gaussians, tiny_scene.cameras, steps=0)
    with pytest.raises(ValueError, match="camera"):
        A.finetune(tiny_scene.gaussians, [])
