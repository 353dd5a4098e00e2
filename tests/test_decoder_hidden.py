"""HiDDeN encoder/decoder: shapes, sizes, determinism, and a tiny training run that reduces the loss."""

import pytest
import torch

from gsw.decoder import HiddenDecoder, HiddenEncoder, bit_accuracy, bits_from_logits, ll_subband
from gsw.decoder.pretrain import training as T


def test_shapes_and_parameter_count():
    enc, dec = HiddenEncoder(48), HiddenDecoder(48)
    x, m = torch.rand(2, 3, 64, 40), torch.randint(0, 2, (2, 48)).float()
    r = enc(x, m)
    assert r.shape == x.shape
    ll = ll_subband(x + r)
    assert ll.shape == (2, 3, 16, 10)
    assert dec(ll).shape == (2, 48)
    assert dec(ll_subband(torch.rand(1, 3, 37, 91))).shape == (1, 48)  # any size (global pooling)
    n = sum(p.numel() for p in dec.parameters())
    assert 250_000 < n < 320_000  # 8 x 64-channel blocks + 64->k block + k x k linear
    blocks = [m for m in dec.layers]
    assert len(blocks) == 9 and isinstance(blocks[0][2], torch.nn.GELU)


def test_determinism_and_batch_independence_in_eval():
    torch.manual_seed(0)
    d1 = HiddenDecoder(32).eval()
    torch.manual_seed(0)
    d2 = HiddenDecoder(32).eval()
    ll = ll_subband(torch.rand(4, 3, 64, 64))
    with torch.no_grad():
        a, b = d1(ll), d2(ll)
        assert torch.equal(a, b)
        assert torch.allclose(d1(ll[:1]), a[:1], atol=1e-5)


def test_input_norm_invariances():
    ll = ll_subband(torch.rand(3, 3, 64, 64))
    gain, offset = 0.7, torch.tensor([0.3, -0.2, 0.5]).view(1, 3, 1, 1)
    with torch.no_grad():
        for norm, changed in (("center", ll + offset), ("standardize", ll * gain + offset)):
            torch.manual_seed(0)
            dec = HiddenDecoder(8, num_blocks=2, channels=8, input_norm=norm).eval()
            assert torch.allclose(dec(changed), dec(ll), atol=1e-4), norm
        torch.manual_seed(0)
        raw = HiddenDecoder(8, num_blocks=2, channels=8, input_norm="none").eval()
        assert not torch.allclose(raw(ll + offset), raw(ll), atol=1e-4)
    with pytest.raises(ValueError, match="input_norm"):
        HiddenDecoder(8, input_norm="whiten")


def test_bit_helpers():
    logits = torch.tensor([[2.0, -1.0, 0.5, -0.1]])
    assert torch.equal(bits_from_logits(logits), torch.tensor([[1.0, 0.0, 1.0, 0.0]]))
    assert float(bit_accuracy(logits, torch.tensor([[1.0, 0.0, 0.0, 0.0]]))) == 0.75


def test_embed_hits_target_psnr():
    torch.manual_seed(0)
    enc = HiddenEncoder(8).eval()
    x = torch.rand(3, 3, 32, 32) * 0.5 + 0.25  # away from the clamp
    with torch.no_grad():
        y = T.embed(enc, x, torch.randint(0, 2, (3, 8)).float(), psnr=30.0)
    psnr = -10 * torch.log10((y - x).pow(2).mean((1, 2, 3)))
    assert torch.allclose(psnr, torch.full((3,), 30.0), atol=0.05)


def test_tiny_training_run_reduces_loss(tmp_path):
    g = torch.Generator().manual_seed(0)
    images = [(torch.nn.functional.interpolate(torch.rand(1, 3, 8, 8, generator=g), size=(48, 48),
                                               mode="bilinear")[0] * 255).to(torch.uint8) for _ in range(8)]
    cfg = T.TrainConfig(num_bits=4, channels=8, enc_blocks=1, dec_blocks=2, crop=16, batch_size=16, lr=1e-2,
                        psnr_start=14.0, psnr_target=14.0, steps=20, noise_layers=("identity", "noise"),
                        log_every=5, ckpt_every_s=1e9, seed=0)
    ckpt = tmp_path / "k4.pt"
    torch.manual_seed(0)
    state = T.train(cfg, images, "cpu", ckpt_path=ckpt, verbose=False)
    losses = [e["loss"] for e in state["log"]]
    assert len(losses) == 4
    assert losses[-1] < losses[0] - 0.05, losses
    assert ckpt.exists()
    # resuming a finished run is a no-op that keeps the step count
    cfg.steps = 21
    state2 = T.train(cfg, images, "cpu", ckpt_path=ckpt, verbose=False)
    assert state2["step"] == 21


def test_template_encoder_keys_bits_by_pattern():
    torch.manual_seed(0)
    enc = T.TemplateEncoder(HiddenEncoder(4, num_blocks=1, channels=8), side=4).eval()
    x = torch.rand(1, 3, 32, 32)
    m0 = torch.tensor([[0.0, 1.0, 0.0, 1.0]])
    m1 = m0.clone()
    m1[0, 0] = 1.0
    with torch.no_grad():
        r0, r0b, r1 = enc(x, m0), enc(x, m0), enc(x, m1)
        hidden_delta = enc.hidden(x, m1) - enc.hidden(x, m0)
    assert r0.shape == x.shape and torch.equal(r0, r0b)  # eval: no random phase
    # flipping bit 0 swaps its template (P0 -> P1) on top of the HiDDeN residual's own change
    tpl = (r1 - r0) - hidden_delta
    assert tpl.abs().max() > 1e-3
    # periodic with 4 LL2 px = 16 px (away from the borders, where the bilinear upsampling clamps)
    assert torch.allclose(tpl[..., 2:14, 2:14], tpl[..., 18:30, 18:30], atol=1e-5)
