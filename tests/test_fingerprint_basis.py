"""gsw.fingerprint.basis: the bit basis combines its offsets as documented, fits deterministically, and a pool
started from it hands out recipients whose start already passes without a step."""

from __future__ import annotations

import pytest
import torch

from gsw.fingerprint.basis import BasisConfig, BitBasis, fit_basis, scene_basis
from gsw.fingerprint.batched import finetune_batch
from gsw.fingerprint.shared import prepare_scene, worker_scene
from gsw.fingerprint.stopping import EarlyStop
from gsw.mark.embed import EmbedConfig
from gsw.mark.loss import LossWeights
from gsw.scenes import default_scene


def _scene(size: int = 32, cams: int = 3):
    scene = default_scene(width=size, height=size, n_cameras=cams, detail=0.2)
    bg = tuple(float(v) for v in scene.background)
    cfg = EmbedConfig(epochs=1, lpips_net=None, weights=LossWeights(lpips=0.0, message=1.0), background=bg)
    return worker_scene(prepare_scene(scene.gaussians, scene.cameras, config=cfg), "cpu")


def test_config_parse_and_errors() -> None:
    assert BasisConfig.parse("") == BasisConfig()
    assert BasisConfig.parse("steps=5,batch=2,seed=3") == BasisConfig(5, 2, 3)
    with pytest.raises(ValueError, match="bad bit-basis setting 'lr=1'"):
        BasisConfig.parse("lr=1")
    with pytest.raises(ValueError, match="needs an integer"):
        BasisConfig.parse("steps=x")
    with pytest.raises(ValueError, match="steps >= 1"):
        BasisConfig(steps=0)


def test_combine_is_the_signed_sum_of_the_offsets() -> None:
    scene = default_scene(width=32, height=32, n_cameras=2, detail=0.2)
    k = 4
    basis = BitBasis(scene.gaussians, k, EmbedConfig(lpips_net=None))
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for t in (basis.params.dc, basis.params.rest, basis.params.logits):
            t.add_(torch.randn(t.shape, generator=gen))
    message = torch.tensor([1.0, 0.0, 0.0, 1.0])
    s = 2 * message - 1
    start = basis.start(message)
    p, g = basis.params, scene.gaussians
    want_dc = p.dc[0] + sum(s[i] * (p.dc[i + 1] - g.sh[:, :1]) for i in range(k))
    want_logits = p.logits[0] + sum(s[i] * (p.logits[i + 1] - g.opacity_logits) for i in range(k))
    assert torch.allclose(start["dc"], want_dc, atol=1e-5)
    assert torch.allclose(start["logits"], want_logits, atol=1e-5)
    assert torch.equal(start["quats"], g.quats)  # untouched offsets: the model itself
    # models() is differentiable in the offsets
    models = basis.models(s[None])
    models[0].sh.sum().backward()
    assert p.dc.grad is not None and float(p.dc.grad[1:].abs().sum()) > 0


def test_fit_is_deterministic_and_cached() -> None:
    ws = _scene()
    a = fit_basis(ws, BasisConfig(steps=2, batch=2, seed=1))
    b = fit_basis(ws, BasisConfig(steps=2, batch=2, seed=1))
    assert torch.equal(a.params.dc, b.params.dc) and torch.equal(a.params.logits, b.params.logits)
    assert not torch.equal(a.params.dc[1], ws.model.sh[:, :1])  # the bit offsets moved
    cfg = BasisConfig(steps=1, batch=1)
    assert scene_basis(ws, cfg) is scene_basis(ws, cfg)


def test_fit_refuses_train_time_attacks() -> None:
    scene = default_scene(width=32, height=32, n_cameras=2, detail=0.2)
    cfg = EmbedConfig(epochs=1, lpips_net=None, weights=LossWeights(lpips=0.0), attacks=0.5)
    ws = worker_scene(prepare_scene(scene.gaussians, scene.cameras, config=cfg), "cpu")
    with pytest.raises(ValueError, match="without train-time image attacks"):
        fit_basis(ws, BasisConfig(steps=1))


def test_pool_starts_from_the_basis_and_hands_out_ready_starts() -> None:
    ws = _scene()
    basis = fit_basis(ws, BasisConfig(steps=1, batch=1))
    messages = torch.randint(0, 2, (3, 32), generator=torch.Generator().manual_seed(0)).float()
    # without a stopping rule every recipient runs the cap from its basis start
    res = finetune_batch(ws, ["a", "b", "c"], messages, slots=2, basis=basis)
    cap = ws.shared.config.epochs * len(ws.shared.cameras)
    assert [r.steps for r in res] == [cap] * 3
    # a rule whose confirmation every start passes: no recipient takes a step
    lenient = EarlyStop(min_steps=1, window=1, margin=0.0, confirm=0.0)
    copies = []
    res = finetune_batch(ws, ["a", "b", "c"], messages, slots=2, stop=lenient, basis=basis, on_copy=copies.append)
    assert [r.steps for r in res] == [0, 0, 0] and all(r.stopped_early for r in res)
    assert [c.name for c in copies] == ["a", "b", "c"]
    start = basis.start(messages[1])
    assert torch.equal(res[1].gaussians.sh[:, :1], start["dc"].cpu())
