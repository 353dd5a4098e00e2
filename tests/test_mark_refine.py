"""Decoder-guided refinement of a watermark residual (gsw.mark.refine)."""

import pytest
import torch
import torch.nn.functional as F

from gsw.decoder import load_decoder
from gsw.decoder.pretrain import encoders as T
from gsw.decoder.dwt import ll_subband
from gsw.metrics.image import psnr
from gsw.decoder.hidden import HiddenDecoder, HiddenEncoder
from gsw.mark.refine import attack_cycle, refine_residual, scale_to_psnr


def _decoder(k: int = 16) -> HiddenDecoder:
    torch.manual_seed(0)
    return HiddenDecoder(k, num_blocks=2, channels=16, input_norm="standardize").eval()


def test_scale_to_psnr_sets_each_images_psnr():
    r = torch.randn(3, 3, 20, 24) * torch.tensor([0.1, 1.0, 7.0])[:, None, None, None]
    x = torch.full((3, 3, 20, 24), 0.5)
    assert torch.allclose(psnr(x + scale_to_psnr(r, 33.0), x), torch.full((3,), 33.0), atol=1e-3)


def test_zero_steps_is_the_start_rescaled_and_clamped():
    x, r = torch.rand(2, 3, 32, 32), torch.randn(2, 3, 32, 32)
    m = torch.randint(0, 2, (2, 16)).float()
    out = refine_residual(_decoder(), x, r * 5.0, m, psnr=30.0, steps=0)
    assert torch.allclose(out, (x + scale_to_psnr(r, 30.0)).clamp(0, 1))


def test_refinement_writes_the_message_at_the_psnr_without_touching_the_decoder():
    dec = load_decoder(32).decoder.eval()  # the shipped 32-bit decoder, raw logits
    before = {n: p.clone() for n, p in dec.state_dict().items()}
    gen = torch.Generator().manual_seed(1)
    x = 0.2 + 0.6 * F.interpolate(torch.rand(4, 3, 12, 12, generator=gen), size=(96, 96), mode="bilinear")
    m = torch.randint(0, 2, (4, 32), generator=gen).float()
    r0 = torch.randn(4, 3, 96, 96, generator=gen)  # noise: no message in it

    def acc(y):
        return ((dec(ll_subband(y)) > 0).float() == m).float().mean().item()

    start = acc(refine_residual(dec, x, r0, m, psnr=30.0, steps=0))
    out = refine_residual(dec, x, r0, m, psnr=30.0, steps=30, lr=0.3)
    assert start < 0.7 and acc(out) == 1.0  # from chance to every bit
    assert torch.allclose(psnr(out, x), torch.full((4,), 30.0), atol=0.05)  # the PSNR is kept
    assert all(torch.equal(before[n], v) for n, v in dec.state_dict().items())
    assert all(p.grad is None for p in dec.parameters())


def test_refinement_goes_through_the_attack_each_step():
    seen = []

    def attack(y, step):
        seen.append(step)
        assert y.requires_grad  # the attack sits inside the graph
        return y.flip(-1)

    x, m = torch.rand(1, 3, 32, 32), torch.randint(0, 2, (1, 16)).float()
    refine_residual(_decoder(), x, torch.randn_like(x), m, psnr=30.0, steps=3, attack=attack)
    assert seen == [0, 1, 2]
    clean = refine_residual(_decoder(), x, torch.ones_like(x), m, psnr=30.0, steps=3)
    skipped = refine_residual(_decoder(), x, torch.ones_like(x), m, psnr=30.0, steps=3, attack=lambda y, s: None)
    assert torch.equal(clean, skipped)  # an attack that returns None leaves the clean loss alone
    with pytest.raises(ValueError, match="steps must be >= 0"):
        refine_residual(_decoder(), x, torch.randn_like(x), m, psnr=30.0, steps=-1)
    with pytest.raises(ValueError, match="schedule must be one of"):
        refine_residual(_decoder(), x, torch.randn_like(x), m, psnr=30.0, schedule="linear")


def test_attack_cycle_takes_the_attacks_in_turn_on_every_nth_step():
    calls = []

    def apply(name, y, strength):
        calls.append((name, strength))
        return y + 1.0

    attack = attack_cycle(apply, ["a", "b", "c"], every=2)
    y = torch.zeros(1, 3, 4, 4)
    out = [attack(y, step) for step in range(8)]
    assert [o is None for o in out] == [False, True] * 4  # odd steps stay clean
    assert torch.equal(out[0], y + 1.0)
    assert calls == [("a", 1.0), ("b", 1.0), ("c", 1.0), ("a", 1.0)]
    with pytest.raises(ValueError, match="every must be >= 1"):
        attack_cycle(apply, ["a"], every=0)
    with pytest.raises(ValueError, match="names must not be empty"):
        attack_cycle(apply, [])


def test_embed_scaled_is_the_encoder_residual_at_the_psnr():
    torch.manual_seed(2)
    enc = HiddenEncoder(8, num_blocks=1, channels=8).eval()
    x, m = torch.rand(2, 3, 40, 56), torch.randint(0, 2, (2, 8)).float()
    for down in (1, 2):
        with torch.no_grad():
            want = (x + scale_to_psnr(T.encoder_residual(enc, x, m, down), 30.0)).clamp(0, 1)
            assert torch.allclose(T.embed_scaled(enc, x, m, 30.0, down), want, atol=1e-6)
