"""gsw.fingerprint.batched: K recipients fine-tuned together get what each would get alone."""

from __future__ import annotations

import pytest
import torch

from gsw.decoder.zoo import load_decoder
from gsw.fingerprint.batched import BatchedParams, batched_loss, finetune_batch
from gsw.fingerprint.shared import prepare_scene, worker_scene
from gsw.mark.embed import EmbedConfig
from gsw.mark.loss import LossWeights, WatermarkLoss
from gsw.mark.message import as_message
from gsw.scenes import default_scene


@pytest.mark.parametrize("lpips_net", [None, "alex"])  # with alex: LPIPS per sample in one batch
def test_batched_loss_is_the_sum_of_the_single_losses(lpips_net) -> None:
    torch.manual_seed(0)
    weights = LossWeights(lpips=0.0) if lpips_net is None else LossWeights()
    loss = WatermarkLoss(load_decoder(32), weights, lpips_net)
    renders = torch.rand(3, 3, 64, 64, requires_grad=True)
    original = torch.rand(3, 64, 64)
    messages = torch.randint(0, 2, (3, 32)).float()
    total, logits = batched_loss(loss, renders, original, messages)
    total.backward()
    single = renders.detach().clone().requires_grad_()
    parts = [loss(single[j], original, messages[j]) for j in range(3)]
    sum(p[0] for p in parts).backward()
    assert torch.allclose(total, sum(p[0] for p in parts).detach(), rtol=1e-5)
    assert torch.allclose(logits, torch.stack([p[2] for p in parts]), rtol=1e-4, atol=1e-3)  # batched convs
    assert torch.allclose(renders.grad, single.grad, rtol=1e-3, atol=1e-6)


def test_stacked_parameters_start_from_the_model() -> None:
    scene = default_scene(width=32, height=32, n_cameras=2, detail=0.2)
    params = BatchedParams(scene.gaussians, 3, EmbedConfig(lpips_net=None))
    assert params.dc.shape == (3, len(scene.gaussians), 1, 3)
    for j in range(3):
        g = params.gaussians(j)
        assert torch.equal(g.sh, scene.gaussians.sh) and torch.equal(g.quats, scene.gaussians.quats)
    assert not params.means.requires_grad  # positions are shared and frozen by default
    assert all(torch.equal(m[0], m[2]) for m in params.mask.masks)  # per-copy masks are the copies' own


def test_batch_matches_one_at_a_time() -> None:
    scene = default_scene(width=64, height=64, n_cameras=3, detail=0.3)
    bg = tuple(float(v) for v in scene.background)
    cfg = EmbedConfig(epochs=1, lpips_net=None, weights=LossWeights(lpips=0.0, message=1.0), background=bg)
    ws = worker_scene(prepare_scene(scene.gaussians, scene.cameras, config=cfg), "cpu")
    messages = torch.stack([as_message("c0ffee42", 32), as_message("12345678", 32)])
    steps = []
    both = finetune_batch(ws, ["a", "b"], messages, on_step=steps.append)
    alone = finetune_batch(ws, ["b"], messages[1:])[0]
    assert steps == [2, 2, 2]
    assert [r.name for r in both] == ["a", "b"]
    # the same optimisation up to float summation order (Adam with eps 1e-15 amplifies tiny differences)
    assert abs(both[1].psnr - alone.psnr) < 0.2
    assert abs(both[1].bit_accuracy - alone.bit_accuracy) <= 2 / 32
    assert (both[1].gaussians.sh - alone.gaussians.sh).abs().mean() < 1e-3
    # while the two recipients' copies differ
    assert (both[0].gaussians.sh - both[1].gaussians.sh).abs().mean() > 1e-3
    assert all(0 <= r.min_bit_accuracy <= r.bit_accuracy <= 1 and r.min_psnr <= r.psnr for r in both)


def test_model_attacks_are_refused() -> None:
    scene = default_scene(width=32, height=32, n_cameras=2, detail=0.2)
    cfg = EmbedConfig(epochs=1, lpips_net=None, weights=LossWeights(lpips=0.0), model_attacks=0.5)
    ws = worker_scene(prepare_scene(scene.gaussians, scene.cameras, config=cfg), "cpu")
    with pytest.raises(ValueError, match="model attacks"):
        finetune_batch(ws, ["a"], torch.zeros(1, 32))
