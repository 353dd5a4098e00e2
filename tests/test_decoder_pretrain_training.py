"""Decoder-training helpers of gsw.decoder.pretrain.training (device attacks, multi-bit trainer)."""

import math

import pytest
import torch

from gsw.decoder.pretrain import training as T


def _ramp(h: int = 32, w: int = 48) -> torch.Tensor:
    y, x = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    return torch.stack([x, y, 0.5 * (x + y)])[None].repeat(2, 1, 1, 1)


def test_view_warp_strength_zero_is_identity():
    x = _ramp()
    y = T.GpuAttacks(torch.device("cpu"), 0).view(x, 0.0)
    assert y.shape == x.shape
    assert torch.allclose(y, x, atol=1e-5)


def test_view_warp_deterministic_in_range_and_changes_the_image():
    x = _ramp()
    a = T.GpuAttacks(torch.device("cpu"), 3).view(x, 1.0)
    b = T.GpuAttacks(torch.device("cpu"), 3).view(x, 1.0)
    assert torch.equal(a, b)
    assert a.shape == x.shape and a.min() >= 0.0 and a.max() <= 1.0
    assert (a - x).abs().mean() > 0.05


def test_view_warp_rotation_of_a_radial_pattern_is_invisible():
    # only rotation (no zoom, no foreshortening): a centred radial pattern is unchanged away from the border
    h = w = 65
    y, x = torch.meshgrid(torch.arange(h) - 32.0, torch.arange(w) - 32.0, indexing="ij")
    img = (0.5 + 0.5 * torch.cos((x**2 + y**2).sqrt() / 3.0)).expand(1, 3, h, w)
    out = T.GpuAttacks(torch.device("cpu"), 1).view(img, 1.0, max_zoom=1.0, min_foreshortening=1.0)
    inner = (x**2 + y**2).sqrt() < 24
    assert (out[0, 0] - img[0, 0])[inner].abs().max() < 0.1  # bilinear resampling error only


def test_train_multi_with_view_warp_runs_and_logs():
    gen = torch.Generator().manual_seed(0)
    bank = (torch.rand(4, 3, 40, 40, generator=gen) * 255).to(torch.uint8)
    cfg = T.MultiConfig(bits=(8,), channels=8, enc_blocks=1, dec_blocks=2, crop=32, batch_size=4, steps=3,
                        amp=False, channels_last=False, log_every=1, clean_frac=0.0, view_warp=True)
    st = T.train_multi(cfg, bank, verbose=False)
    assert st["step"] == 3 and len(st["log"]) == 3
    assert all(math.isfinite(e["loss"]) for e in st["log"])
    assert st["log"][-1]["strength"] > 0  # the warp (and attacks) were on


def test_train_multi_clean_chunk_keeps_half_of_every_batch_unattacked():
    gen = torch.Generator().manual_seed(0)
    bank = (torch.rand(4, 3, 40, 40, generator=gen) * 255).to(torch.uint8)
    cfg = T.MultiConfig(bits=(8,), channels=8, enc_blocks=1, dec_blocks=2, crop=32, batch_size=4, steps=6,
                        amp=False, channels_last=False, log_every=1, clean_frac=0.0, noise_chunks=2,
                        noise_layers=("identity", "noise", "blur", "jpeg"), clean_chunk=True)
    st = T.train_multi(cfg, bank, verbose=False)
    assert all("identity" in e["k8"] for e in st["log"])  # every step decoded a clean chunk ...
    assert any(set(e["k8"]) - {"identity"} for e in st["log"])  # ... beside an attacked one


def test_balance_loss_zero_when_every_bit_is_split_in_half_and_one_when_constant():
    half = torch.tensor([[20.0, -20.0], [-20.0, 20.0]])  # each bit 1 on one image of two
    assert float(T.balance_loss(half)) < 1e-12
    assert abs(float(T.balance_loss(torch.full((5, 3), 30.0))) - 1.0) < 1e-6
    assert abs(float(T.balance_loss(torch.full((5, 3), -30.0))) - 1.0) < 1e-6
    x = torch.tensor([[1.0, 2.0], [0.5, -0.1]], requires_grad=True)
    T.balance_loss(x).backward()
    assert (x.grad > 0).all()  # both bits lean to 1: descent lowers every logit


def test_train_multi_balance_loss_unbiases_an_unmarked_decoder():
    gen = torch.Generator().manual_seed(0)
    bank = (torch.rand(8, 3, 48, 48, generator=gen) * 255).to(torch.uint8)
    cfg = T.MultiConfig(bits=(4,), channels=8, enc_blocks=1, dec_blocks=2, crop=32, batch_size=8, steps=100,
                        amp=False, channels_last=False, log_every=10, clean_frac=1.0, lr=1e-2,
                        balance=10.0, balance_batch=16, balance_sizes=(32, 48), freeze_bn=True)
    dec = T.HiddenDecoder(4, 2, 8, cfg.dec_norm)
    with torch.no_grad():
        dec.linear.bias.fill_(3.0)  # every bit 1 on every image
    cover = T.bank_crops(bank, 64, 40, torch.Generator().manual_seed(5))
    ll = T.ll_subband(cover)

    def p1_dev() -> float:
        dec.eval()
        with torch.no_grad():
            return float(((dec(ll) > 0).float().mean(0) - 0.5).abs().mean())

    assert p1_dev() == 0.5
    bn_before = [b.running_mean.clone() for b in dec.modules() if isinstance(b, torch.nn.BatchNorm2d)]
    st = T.train_multi(cfg, bank, decoders=[dec], verbose=False)
    bal = [e["balance"]["k4"] for e in st["log"]]
    assert bal[-1] < 0.6 * bal[0]
    assert p1_dev() < 0.4
    bn_after = [b.running_mean for b in dec.modules() if isinstance(b, torch.nn.BatchNorm2d)]
    assert all(torch.equal(a, b) for a, b in zip(bn_before, bn_after))  # freeze_bn: statistics untouched


def test_template_encoder_mlp_branch_starts_at_zero_and_learns():
    torch.manual_seed(0)
    hidden = T.HiddenEncoder(8, num_blocks=1, channels=8)
    plain = T.TemplateEncoder(hidden, side=4).eval()
    with_mlp = T.TemplateEncoder(hidden, side=4, mlp=16).eval()
    with_mlp.load_grown_state_dict(plain.state_dict())
    x, m = torch.rand(2, 3, 24, 40), torch.randint(0, 2, (2, 8)).float()
    assert torch.equal(with_mlp(x, m), plain(x, m))  # adding the branch changes nothing ...
    with_mlp(x, m).pow(2).sum().backward()
    assert with_mlp.mlp[-1].weight.grad.abs().sum() > 0  # ... until it is trained
    m2 = m.clone()
    m2[:, 0] = 1 - m2[:, 0]
    with torch.no_grad():
        with_mlp.mlp[-1].weight.normal_()
    assert not torch.allclose(with_mlp(x, m) - plain(x, m), with_mlp(x, m2) - plain(x, m2))  # message-dependent


def test_template_encoder_refiner_starts_at_zero_and_adapts_to_the_image():
    torch.manual_seed(2)
    small = T.TemplateEncoder(T.HiddenEncoder(8, num_blocks=1, channels=8), side=4, mlp=16).eval()
    refined = T.TemplateEncoder(T.HiddenEncoder(8, num_blocks=1, channels=8), side=4, mlp=16, refine=12).eval()
    refined.load_grown_state_dict(small.state_dict())
    x, m = torch.rand(2, 3, 36, 52), torch.randint(0, 2, (2, 8)).float()
    assert torch.equal(refined(x, m), small(x, m))  # the refiner starts at zero
    refined(x, m).pow(2).sum().backward()
    assert refined.refine[-1].weight.grad.abs().sum() > 0
    with torch.no_grad():
        refined.refine[-1].weight.normal_()
        x2 = x.flip(-1)  # the same pixel statistics, another image
        # image-agnostic before: the pattern (residual minus the HiDDeN part) does not depend on the image
        pat = lambda enc, im: enc(im, m) - enc.hidden(im, m)  # noqa: E731
        assert torch.allclose(pat(small, x), pat(small, x2), atol=1e-6)
        assert not torch.allclose(pat(refined, x), pat(refined, x2), atol=1e-3)  # image-adaptive after
    with pytest.raises(ValueError, match="refine branch, this encoder has none"):
        small.load_grown_state_dict(refined.state_dict())


def test_template_encoder_grows_without_changing_its_residual():
    torch.manual_seed(1)
    hidden = T.HiddenEncoder(8, num_blocks=1, channels=8)
    small = T.TemplateEncoder(hidden, side=4, mlp=16)
    with torch.no_grad():
        small.mlp[-1].weight.normal_()  # a trained (non-zero) branch
    small.eval()
    big = T.TemplateEncoder(T.HiddenEncoder(8, num_blocks=1, channels=8), side=8, mlp=64).eval()
    big.load_grown_state_dict(small.state_dict())  # templates 4 -> 8 (tiled), mlp 16 -> 64 (widened)
    x, m = torch.rand(3, 3, 40, 56), torch.randint(0, 2, (3, 8)).float()
    assert torch.allclose(big(x, m), small(x, m), atol=1e-5)
    big(x, m).pow(2).sum().backward()
    assert big.mlp[0].weight.grad[16:].abs().sum() == 0  # new units are dead until their outputs move ...
    assert big.mlp[-1].weight.grad[:, 16:].abs().sum() > 0  # ... which they can


def test_template_encoder_growth_errors():

    small = T.TemplateEncoder(T.HiddenEncoder(8, num_blocks=1, channels=8), side=4, mlp=16)
    with pytest.raises(ValueError, match="side 4 cannot grow to side 6"):
        T.TemplateEncoder(T.HiddenEncoder(8, num_blocks=1, channels=8), side=6, mlp=16).load_grown_state_dict(
            small.state_dict())
    with pytest.raises(ValueError, match="cannot shrink"):
        T.TemplateEncoder(T.HiddenEncoder(8, num_blocks=1, channels=8), side=4, mlp=8).load_grown_state_dict(
            small.state_dict())
    with pytest.raises(ValueError, match="has none"):
        T.TemplateEncoder(T.HiddenEncoder(8, num_blocks=1, channels=8), side=4).load_grown_state_dict(
            small.state_dict())


def test_load_run_encoder_reads_full_and_float16_checkpoints(tmp_path):
    import dataclasses
    import json

    cfg = T.MultiConfig(bits=(8,), channels=8, enc_blocks=1, templates=4, template_mlp=16, enc_down=2)
    torch.manual_seed(3)
    enc = T.make_encoder(8, cfg).eval()
    meta = {"config": {**dataclasses.asdict(cfg), "num_bits": 8, "ft_s": 1.0}}
    full, half, compact = tmp_path / "full", tmp_path / "half", tmp_path / "compact"
    for d in (full, half, compact):
        d.mkdir()
        (d / "k8.json").write_text(json.dumps(meta))
    torch.save({"encoder_ft": enc.state_dict()}, full / "k8.pt")
    torch.save({"encoder_ft": {n: v.half() if v.is_floating_point() else v for n, v in enc.state_dict().items()}},
               half / "k8.encoder_ft16.pt")
    torch.save({"encoder_ft": torch.load(half / "k8.encoder_ft16.pt")["encoder_ft"]}, compact / "k8.pt")  # --half
    x, m = torch.rand(2, 3, 32, 40), torch.randint(0, 2, (2, 8)).float()
    loaded, lcfg = T.load_run_encoder(full, 8)
    assert lcfg.template_mlp == 16 and lcfg.enc_down == 2 and not loaded.training
    with torch.no_grad():
        assert torch.equal(loaded(x, m), enc(x, m))
        assert torch.allclose(T.load_run_encoder(half, 8)[0](x, m), enc(x, m), atol=1e-2)  # float16 weights
        assert torch.equal(T.load_run_encoder(compact, 8)[0](x, m), T.load_run_encoder(half, 8)[0](x, m))
    with pytest.raises(FileNotFoundError, match="neither k8.pt"):
        T.load_run_encoder(half, 8, key="encoder")
