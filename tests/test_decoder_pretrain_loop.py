"""The host-side pre-training loop (gsw.decoder.pretrain.loop) and its schedule helpers."""

import torch

from gsw.decoder.pretrain.config import TrainConfig
from gsw.decoder.pretrain.loop import chunks, lr_factor, ramp, train


def test_schedule_helpers():
    assert [(s.start, s.stop) for s in chunks(10, 3)] == [(0, 3), (3, 7), (7, 10)]
    assert ramp(0.1, 0.2) == 0.5 and ramp(0.5, 0.2) == 1.0 and ramp(0.0, 0.0) == 1.0
    assert lr_factor(0.0, 0.1) == 1e-3 and abs(lr_factor(0.05, 0.1) - 0.5) < 1e-12
    assert abs(lr_factor(0.1, 0.1) - 1.0) < 1e-12 and abs(lr_factor(1.0, 0.1) - 0.02) < 1e-12


def test_tiny_training_run_reduces_loss(tmp_path):
    g = torch.Generator().manual_seed(0)
    images = [(torch.nn.functional.interpolate(torch.rand(1, 3, 8, 8, generator=g), size=(48, 48),
                                               mode="bilinear")[0] * 255).to(torch.uint8) for _ in range(8)]
    cfg = TrainConfig(num_bits=4, channels=8, enc_blocks=1, dec_blocks=2, crop=16, batch_size=16, lr=1e-2,
                      psnr_start=14.0, psnr_target=14.0, steps=20, noise_layers=("identity", "noise"),
                      log_every=5, ckpt_every_s=1e9, seed=0)
    ckpt = tmp_path / "k4.pt"
    torch.manual_seed(0)
    state = train(cfg, images, "cpu", ckpt_path=ckpt, verbose=False)
    losses = [e["loss"] for e in state["log"]]
    assert len(losses) == 4
    assert losses[-1] < losses[0] - 0.05, losses
    assert ckpt.exists()
    # resuming a finished run is a no-op that keeps the step count
    cfg.steps = 21
    state2 = train(cfg, images, "cpu", ckpt_path=ckpt, verbose=False)
    assert state2["step"] == 21
