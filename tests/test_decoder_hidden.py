"""HiDDeN encoder/decoder: shapes, sizes, determinism, input normalisation, bit helpers, PSNR scaling."""

import pytest
import torch

from gsw.decoder import HiddenDecoder, HiddenEncoder, bit_accuracy, bits_from_logits, ll_subband
from gsw.decoder.hidden import scale_to_psnr


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


def test_scale_to_psnr_sets_each_images_rms():
    r = torch.randn(3, 3, 8, 8) * torch.tensor([0.1, 1.0, 10.0])[:, None, None, None]
    out = scale_to_psnr(r, 30.0)
    rms = out.pow(2).mean((1, 2, 3)).sqrt()
    assert torch.allclose(rms, torch.full((3,), 10 ** (-30 / 20)), rtol=1e-4)
    assert torch.allclose(out / out.flatten(1).norm(dim=1)[:, None, None, None],
                          r / r.flatten(1).norm(dim=1)[:, None, None, None], atol=1e-6)  # direction kept


def test_fold_batchnorm_is_the_same_function_with_fewer_layers() -> None:
    """The shipped decoder with its BatchNorms folded into the convolutions reads the same logits and passes the
    same input gradient; the original stays untouched; a network in training mode is refused."""
    from gsw.decoder.hidden import fold_batchnorm
    from gsw.decoder.zoo import load_decoder

    dec = load_decoder(32).eval().requires_grad_(False).double()  # float64: the fold is exact up to rounding
    folded = fold_batchnorm(dec)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in dec.modules())
    x = torch.rand(2, 3, 40, 40, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    xa, xb = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    ya, yb = dec(xa), folded(xb)
    torch.testing.assert_close(yb, ya, rtol=1e-10, atol=1e-10)
    ya.square().sum().backward()
    yb.square().sum().backward()
    torch.testing.assert_close(xb.grad, xa.grad, rtol=1e-10, atol=1e-9)
    assert all(not p.requires_grad for p in folded.parameters())
    with pytest.raises(ValueError, match="eval mode"):
        fold_batchnorm(HiddenDecoder(8).train())
