"""Train-time model distortions (gsw.attacks.distort): straight-through exports equal the real codecs' round
trips, gradients pass, draws are deterministic under a seed; the export attacks of gsw.attacks.model."""

from __future__ import annotations

import random

import pytest
import torch
from helpers import random_model

from gsw.attacks import distort as D
from gsw.attacks.model import export_compressed_ply, export_splat, export_spz, quantize
from gsw.gaussians import Gaussians
from gsw.io.splat import load_splat, save_splat
from gsw.io.spz import load_spz, save_spz

FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def _model(degree: int = 3, n: int = 400) -> Gaussians:
    g = random_model(n, degree=degree, seed=5)
    # spread the SH rest over the codec's range and include exact quantisation ties and extreme opacities
    sh = g.sh.clone()
    sh[:, 1:] *= 0.8
    sh[:8, 1:] = torch.arange(-4, 4, dtype=torch.float32).view(8, 1, 1) / 128.0 * 4.5
    logits = g.opacity_logits.clone()
    logits[:3] = torch.tensor([-30.0, 0.0, 30.0])
    return Gaussians(g.means * 3, g.log_scales, g.quats, logits, sh)


def _assert_same(a: Gaussians, b: Gaussians, atol: float = 0.0) -> None:
    assert a.sh.shape == b.sh.shape
    for f in FIELDS:
        x, y = getattr(a, f).detach(), getattr(b, f).detach()
        assert torch.allclose(x, y, atol=atol, rtol=0), (f, float((x - y).abs().max()))


def test_splat_st_forward_is_a_real_splat_round_trip(tmp_path):
    g = _model()
    save_splat(g, tmp_path / "m.splat")
    _assert_same(D.splat_st(g), load_splat(tmp_path / "m.splat"), atol=2e-6)


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_spz_st_forward_is_a_real_spz_round_trip(tmp_path, degree):
    g = _model(degree)
    save_spz(g, tmp_path / "m.spz")
    real = load_spz(tmp_path / "m.spz")
    st = D.spz_st(g)
    # a quaternion and its negation are one rotation: compare up to sign
    sign = torch.where((st.quats * real.quats).sum(1, keepdim=True) < 0, -1.0, 1.0)
    _assert_same(Gaussians(st.means, st.log_scales, st.quats * sign, st.opacity_logits, st.sh), real, atol=2e-6)
    assert torch.equal((st.quats * sign).detach(), st.quats.detach())  # same sign, not only same rotation


def test_spz_st_large_scene_uses_fewer_fractional_bits(tmp_path):
    g = _model(1)
    g = Gaussians(g.means * 2000, g.log_scales, g.quats, g.opacity_logits, g.sh)
    save_spz(g, tmp_path / "m.spz")
    _assert_same(D.spz_st(g), load_spz(tmp_path / "m.spz"), atol=1e-3)


def test_quantize_st_forward_is_quantize():
    g = _model()
    _assert_same(D.quantize_st(g), quantize(g, 8), atol=1e-6)  # x + (q - x) rounds in float32


@pytest.mark.parametrize("op", [D.splat_st, D.spz_st, D.quantize_st, D.sh0])
def test_straight_through_gradients_reach_the_kept_parameters(op):
    g = _model(1, 50).requires_grad_(True)
    out = op(g)
    (out.means.sum() + out.log_scales.sum() + out.quats.sum() + out.opacity_logits.sum() + out.sh.sum()).backward()
    for f in ("means", "log_scales", "quats", "opacity_logits"):
        assert torch.equal(getattr(g, f).grad, torch.ones_like(getattr(g, f))), f
    assert torch.equal(g.sh.grad[:, 0], torch.ones_like(g.sh[:, 0]))
    rest_grad = 0.0 if op in (D.splat_st, D.sh0) else 1.0
    assert torch.equal(g.sh.grad[:, 1:], torch.full_like(g.sh[:, 1:], rest_grad))


def test_distort_is_deterministic_under_a_seed():
    g = _model(1, 60)

    def draws(seed):
        rng, gen = random.Random(seed), torch.Generator().manual_seed(seed)
        return [D.distort(g, ("noise", "sh0", "splat", "spz", "8bit"), rng, gen) for _ in range(8)]

    a, b = draws(3), draws(3)
    assert [k for k, _ in a] == [k for k, _ in b] and len({k for k, _ in a}) > 1
    for (_, x), (_, y) in zip(a, b):
        _assert_same(x, y)
    noisy = [m for k, m in draws(4) if k == "noise"] + [D.noise(g, 0.1, torch.Generator().manual_seed(1))]
    assert not torch.equal(noisy[-1].sh, g.sh) and torch.equal(noisy[-1].means, g.means)
    with pytest.raises(ValueError, match="unknown model distortions"):
        D.distort(g, ("blur",), random.Random(0), torch.Generator())


@pytest.mark.parametrize("attack,degree", [(export_splat, 0), (export_spz, 3), (export_compressed_ply, 3)])
def test_export_attacks_round_trip_through_the_real_codecs(attack, degree):
    g = _model()
    out = attack(g)
    assert out.sh_degree == degree and len(out) == len(g) and out.dtype == g.dtype
    assert out.means.data_ptr() != g.means.data_ptr()
    # quantised (something changed) but close: compare the opacities of sorted copies (codecs may reorder)
    a, b = g.opacities.sort().values, out.opacities.sort().values
    assert float((a - b).abs().max()) < 0.01 and not torch.equal(out.sh[:, 0].sort(0).values, g.sh[:, 0].sort(0).values)
