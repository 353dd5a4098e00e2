"""Pre-training encoders (gsw.decoder.pretrain.encoders): PSNR-scaled embedding, template encoders, run files."""

import pytest
import torch

from gsw.decoder.hidden import HiddenEncoder
from gsw.decoder.pretrain import encoders as T
from gsw.decoder.pretrain.config import MultiConfig


def test_embed_hits_target_psnr():
    torch.manual_seed(0)
    enc = HiddenEncoder(8).eval()
    x = torch.rand(3, 3, 32, 32) * 0.5 + 0.25  # away from the clamp
    with torch.no_grad():
        y = T.embed(enc, x, torch.randint(0, 2, (3, 8)).float(), psnr=30.0)
    psnr = -10 * torch.log10((y - x).pow(2).mean((1, 2, 3)))
    assert torch.allclose(psnr, torch.full((3,), 30.0), atol=0.05)


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


def test_template_encoder_mlp_branch_starts_at_zero_and_learns():
    torch.manual_seed(0)
    hidden = HiddenEncoder(8, num_blocks=1, channels=8)
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
    small = T.TemplateEncoder(HiddenEncoder(8, num_blocks=1, channels=8), side=4, mlp=16).eval()
    refined = T.TemplateEncoder(HiddenEncoder(8, num_blocks=1, channels=8), side=4, mlp=16, refine=12).eval()
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
    hidden = HiddenEncoder(8, num_blocks=1, channels=8)
    small = T.TemplateEncoder(hidden, side=4, mlp=16)
    with torch.no_grad():
        small.mlp[-1].weight.normal_()  # a trained (non-zero) branch
    small.eval()
    big = T.TemplateEncoder(HiddenEncoder(8, num_blocks=1, channels=8), side=8, mlp=64).eval()
    big.load_grown_state_dict(small.state_dict())  # templates 4 -> 8 (tiled), mlp 16 -> 64 (widened)
    x, m = torch.rand(3, 3, 40, 56), torch.randint(0, 2, (3, 8)).float()
    assert torch.allclose(big(x, m), small(x, m), atol=1e-5)
    big(x, m).pow(2).sum().backward()
    assert big.mlp[0].weight.grad[16:].abs().sum() == 0  # new units are dead until their outputs move ...
    assert big.mlp[-1].weight.grad[:, 16:].abs().sum() > 0  # ... which they can


def test_template_encoder_growth_errors():

    small = T.TemplateEncoder(HiddenEncoder(8, num_blocks=1, channels=8), side=4, mlp=16)
    with pytest.raises(ValueError, match="side 4 cannot grow to side 6"):
        T.TemplateEncoder(HiddenEncoder(8, num_blocks=1, channels=8), side=6, mlp=16).load_grown_state_dict(
            small.state_dict())
    with pytest.raises(ValueError, match="cannot shrink"):
        T.TemplateEncoder(HiddenEncoder(8, num_blocks=1, channels=8), side=4, mlp=8).load_grown_state_dict(
            small.state_dict())
    with pytest.raises(ValueError, match="has none"):
        T.TemplateEncoder(HiddenEncoder(8, num_blocks=1, channels=8), side=4).load_grown_state_dict(
            small.state_dict())


def test_load_run_encoder_reads_full_and_float16_checkpoints(tmp_path):
    import dataclasses
    import json

    cfg = MultiConfig(bits=(8,), channels=8, enc_blocks=1, templates=4, template_mlp=16, enc_down=2)
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


def test_embed_scaled_at_lower_resolution_keeps_the_psnr_and_the_size():
    torch.manual_seed(0)
    enc = HiddenEncoder(8, num_blocks=1, channels=8).eval()
    x = torch.rand(2, 3, 40, 56) * 0.5 + 0.25
    m = torch.randint(0, 2, (2, 8)).float()
    with torch.no_grad():
        r = T.encoder_residual(enc, x, m, down=2)
        y = T.embed_scaled(enc, x, m, 28.0, down=2)
    assert r.shape == x.shape and y.shape == x.shape
    assert torch.allclose(-10 * torch.log10((y - x).pow(2).mean((1, 2, 3))), torch.full((2,), 28.0), atol=0.05)
    with torch.no_grad():  # the residual of the downsampled image is smoother than the full-resolution one
        full = T.encoder_residual(enc, x, m, down=1)
    tv = lambda t: (t[..., 1:] - t[..., :-1]).abs().mean() / t.abs().mean()  # noqa: E731
    assert tv(r) < tv(full)


def test_to_half_rounds_the_weights_and_encoder_state_stores_float16():
    torch.manual_seed(0)
    enc = HiddenEncoder(8, num_blocks=1, channels=8)
    state = T.encoder_state(enc, half=True)
    assert all(v.dtype == torch.float16 for v in state.values() if v.is_floating_point())
    assert all(v.dtype == torch.float32 for v in T.encoder_state(enc, half=False).values() if v.is_floating_point())
    w = enc.final.weight.detach().clone()
    T.to_half(enc)
    assert enc.final.weight.dtype == torch.float32
    assert torch.equal(enc.final.weight, w.half().float()) and not torch.equal(enc.final.weight, w)
