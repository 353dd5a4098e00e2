"""The device-resident multi-bit trainer (gsw.decoder.pretrain.multi) and the view warp it trains with."""

import math

import torch

from gsw.attacks.layers import GpuAttacks
from gsw.decoder.dwt import ll_subband
from gsw.decoder.hidden import HiddenDecoder
from gsw.decoder.pretrain.config import MultiConfig
from gsw.decoder.pretrain.data import bank_crops
from gsw.decoder.pretrain.multi import balance_loss, schedule, train_multi
from gsw.decoder.whitening import WhiteningLayer


def _ramp(h: int = 32, w: int = 48) -> torch.Tensor:
    y, x = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    return torch.stack([x, y, 0.5 * (x + y)])[None].repeat(2, 1, 1, 1)


def test_view_warp_strength_zero_is_identity():
    x = _ramp()
    y = GpuAttacks(torch.device("cpu"), 0).view(x, 0.0)
    assert y.shape == x.shape
    assert torch.allclose(y, x, atol=1e-5)


def test_view_warp_deterministic_in_range_and_changes_the_image():
    x = _ramp()
    a = GpuAttacks(torch.device("cpu"), 3).view(x, 1.0)
    b = GpuAttacks(torch.device("cpu"), 3).view(x, 1.0)
    assert torch.equal(a, b)
    assert a.shape == x.shape and a.min() >= 0.0 and a.max() <= 1.0
    assert (a - x).abs().mean() > 0.05


def test_view_warp_rotation_of_a_radial_pattern_is_invisible():
    # only rotation (no zoom, no foreshortening): a centred radial pattern is unchanged away from the border
    h = w = 65
    y, x = torch.meshgrid(torch.arange(h) - 32.0, torch.arange(w) - 32.0, indexing="ij")
    img = (0.5 + 0.5 * torch.cos((x**2 + y**2).sqrt() / 3.0)).expand(1, 3, h, w)
    out = GpuAttacks(torch.device("cpu"), 1).view(img, 1.0, max_zoom=1.0, min_foreshortening=1.0)
    inner = (x**2 + y**2).sqrt() < 24
    assert (out[0, 0] - img[0, 0])[inner].abs().max() < 0.1  # bilinear resampling error only


def test_train_multi_with_view_warp_runs_and_logs():
    gen = torch.Generator().manual_seed(0)
    bank = (torch.rand(4, 3, 40, 40, generator=gen) * 255).to(torch.uint8)
    cfg = MultiConfig(bits=(8,), channels=8, enc_blocks=1, dec_blocks=2, crop=32, batch_size=4, steps=3,
                        amp=False, channels_last=False, log_every=1, clean_frac=0.0, view_warp=True)
    st = train_multi(cfg, bank, verbose=False)
    assert st["step"] == 3 and len(st["log"]) == 3
    assert all(math.isfinite(e["loss"]) for e in st["log"])
    assert st["log"][-1]["strength"] > 0  # the warp (and attacks) were on


def test_train_multi_clean_chunk_keeps_half_of_every_batch_unattacked():
    gen = torch.Generator().manual_seed(0)
    bank = (torch.rand(4, 3, 40, 40, generator=gen) * 255).to(torch.uint8)
    cfg = MultiConfig(bits=(8,), channels=8, enc_blocks=1, dec_blocks=2, crop=32, batch_size=4, steps=6,
                        amp=False, channels_last=False, log_every=1, clean_frac=0.0, noise_chunks=2,
                        noise_layers=("identity", "noise", "blur", "jpeg"), clean_chunk=True)
    st = train_multi(cfg, bank, verbose=False)
    assert all("identity" in e["k8"] for e in st["log"])  # every step decoded a clean chunk ...
    assert any(set(e["k8"]) - {"identity"} for e in st["log"])  # ... beside an attacked one


def test_balance_loss_zero_when_every_bit_is_split_in_half_and_one_when_constant():
    half = torch.tensor([[20.0, -20.0], [-20.0, 20.0]])  # each bit 1 on one image of two
    assert float(balance_loss(half)) < 1e-12
    assert abs(float(balance_loss(torch.full((5, 3), 30.0))) - 1.0) < 1e-6
    assert abs(float(balance_loss(torch.full((5, 3), -30.0))) - 1.0) < 1e-6
    x = torch.tensor([[1.0, 2.0], [0.5, -0.1]], requires_grad=True)
    balance_loss(x).backward()
    assert (x.grad > 0).all()  # both bits lean to 1: descent lowers every logit


def test_train_multi_balance_loss_unbiases_an_unmarked_decoder():
    gen = torch.Generator().manual_seed(0)
    bank = (torch.rand(8, 3, 48, 48, generator=gen) * 255).to(torch.uint8)
    cfg = MultiConfig(bits=(4,), channels=8, enc_blocks=1, dec_blocks=2, crop=32, batch_size=8, steps=100,
                        amp=False, channels_last=False, log_every=10, clean_frac=1.0, lr=1e-2,
                        balance=10.0, balance_batch=16, balance_sizes=(32, 48), freeze_bn=True)
    dec = HiddenDecoder(4, 2, 8, cfg.dec_norm)
    with torch.no_grad():
        dec.linear.bias.fill_(3.0)  # every bit 1 on every image
    cover = bank_crops(bank, 64, 40, torch.Generator().manual_seed(5))
    ll = ll_subband(cover)

    def p1_dev() -> float:
        dec.eval()
        with torch.no_grad():
            return float(((dec(ll) > 0).float().mean(0) - 0.5).abs().mean())

    assert p1_dev() == 0.5
    bn_before = [b.running_mean.clone() for b in dec.modules() if isinstance(b, torch.nn.BatchNorm2d)]
    st = train_multi(cfg, bank, decoders=[dec], verbose=False)
    bal = [e["balance"]["k4"] for e in st["log"]]
    assert bal[-1] < 0.6 * bal[0]
    assert p1_dev() < 0.4
    bn_after = [b.running_mean for b in dec.modules() if isinstance(b, torch.nn.BatchNorm2d)]
    assert all(torch.equal(a, b) for a, b in zip(bn_before, bn_after))  # freeze_bn: statistics untouched


def test_schedule_curriculum():
    cfg = MultiConfig(clean_frac=0.3, noise_ramp_end=0.6, psnr_ramp_end=0.8, psnr_start=22.0, psnr_target=30.0)
    _, s0, p0 = schedule(cfg, 0.1)
    assert (s0, p0) == (0.0, 22.0)  # clean phase: no attacks, strong watermark
    _, s1, p1 = schedule(cfg, 0.45)
    assert abs(s1 - 0.5) < 1e-9 and 22.0 < p1 < 30.0
    _, s2, p2 = schedule(cfg, 0.9)
    assert (s2, p2) == (1.0, 30.0)


def test_train_multi_encoder_finetune_trains_only_the_encoders_and_needs_whitenings():
    gen = torch.Generator().manual_seed(0)
    bank = (torch.rand(4, 3, 40, 40, generator=gen) * 255).to(torch.uint8)
    cfg = MultiConfig(bits=(8,), channels=8, enc_blocks=1, dec_blocks=2, crop=32, batch_size=4, steps=2,
                      amp=False, channels_last=False, log_every=1)
    st = train_multi(cfg, bank, verbose=False)
    dec = st["decoders"][0]
    before = {n: v.clone() for n, v in dec.state_dict().items()}
    enc_before = {n: v.clone() for n, v in st["encoders"][0].state_dict().items()}
    try:
        train_multi(cfg, bank, encoders=st["encoders"], decoders=st["decoders"], finetune_encoders=True,
                    verbose=False)
    except ValueError as e:
        assert "whitenings" in str(e)
    else:
        raise AssertionError("a fine-tune without whitenings must fail")
    seen = []
    ft = train_multi(cfg, bank, encoders=st["encoders"], decoders=st["decoders"], whitenings=[WhiteningLayer(8)],
                     finetune_encoders=True, verbose=False, on_step=lambda f, e: seen.append((f, e is not None)))
    assert all(torch.equal(before[n], v) for n, v in dec.state_dict().items())  # decoder (and its BN) frozen
    assert any(not torch.equal(enc_before[n], v) for n, v in ft["encoders"][0].state_dict().items())
    assert seen == [(0.5, True), (1.0, True)]  # the hook sees the progress and every log entry
    assert all(p.requires_grad for p in dec.parameters())  # given back trainable
