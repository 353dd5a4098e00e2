"""Image-space watermarking against a frozen decoder (gsw.mark.refine)."""

import pytest
import torch
import torch.nn.functional as F

from gsw.decoder import load_decoder
from gsw.mark.refine import watermark_images
from gsw.decoder.dwt import ll_subband
from gsw.metrics.image import psnr
from gsw.mark.refine import ATTACKS
from gsw.decoder.pretrain.config import MultiConfig


def _photos(n: int, size: int = 96, seed: int = 1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return 0.2 + 0.6 * F.interpolate(torch.rand(n, 3, 12, 12, generator=gen), size=(size, size), mode="bilinear")


def test_the_attacks_are_the_training_noise_layers():
    assert ATTACKS == MultiConfig.noise_layers and "identity" in ATTACKS and "jpeg" in ATTACKS


def test_writes_the_message_at_the_psnr_without_touching_the_decoder():
    dec = load_decoder(32)  # what gsw.extract reads (whitened)
    before = {n: p.clone() for n, p in dec.state_dict().items()}
    x = _photos(2)
    m = torch.randint(0, 2, (2, 32), generator=torch.Generator().manual_seed(2)).float()

    def acc(y):
        return ((dec(ll_subband(y)) > 0).float() == m).float().mean().item()

    noise = watermark_images(dec, x, m, psnr=30.0, steps=0)
    out = watermark_images(dec, x, m, psnr=30.0, steps=40, attack_every=0)
    assert acc(noise) < 0.75 and acc(out) == 1.0
    assert torch.allclose(psnr(out, x), torch.full((2,), 30.0), atol=0.1)
    assert out.min() >= 0 and out.max() <= 1
    assert all(torch.equal(before[n], v) for n, v in dec.state_dict().items())


def test_same_seed_same_image_other_seed_other_image():
    dec = load_decoder(32)
    x, m = _photos(1), torch.ones(1, 32)
    a = watermark_images(dec, x, m, psnr=30.0, steps=3, attack_every=2, seed=5)
    b = watermark_images(dec, x, m, psnr=30.0, steps=3, attack_every=2, seed=5)
    c = watermark_images(dec, x, m, psnr=30.0, steps=3, attack_every=2, seed=6)
    assert torch.equal(a, b) and not torch.allclose(a, c)


def test_attack_steps_reach_the_callback_and_bad_arguments_fail():
    dec = load_decoder(32)
    x, m = _photos(1, 64), torch.zeros(1, 32)
    seen = []
    watermark_images(dec, x, m, psnr=30.0, steps=4, attack_every=1, callback=lambda s, loss: seen.append(s))
    assert seen == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="attack_every"):
        watermark_images(dec, x, m, psnr=30.0, steps=1, attack_every=-1)
