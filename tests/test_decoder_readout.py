"""gsw.decoder.readout: the flip-antisymmetric KleinReadout - its formula, its symmetry, marks embedded for it."""

import pytest
import torch
import torch.nn.functional as F

import gsw
from gsw.decoder import KleinReadout, load_decoder, ll_subband
from gsw.mark.message import message_from_key


def _images(n: int = 3, h: int = 64, w: int = 48) -> torch.Tensor:
    gen = torch.Generator().manual_seed(7)
    return 0.2 + 0.6 * F.interpolate(torch.rand(n, 3, 9, 9, generator=gen), size=(h, w), mode="bilinear")


@pytest.fixture(scope="module")
def decoder():
    return load_decoder(32).eval().requires_grad_(False)


def test_klein_readout_is_the_four_orientation_formula(decoder):
    ll = ll_subband(_images())
    k = KleinReadout(decoder)
    with torch.no_grad():
        by_hand = (decoder(ll) - decoder(ll.flip(-1)) - decoder(ll.flip(-2)) + decoder(ll.flip(-1).flip(-2))) / 2
        assert k(ll).shape == (3, 32) and k.num_bits == 32
        assert torch.allclose(k(ll), by_hand, rtol=1e-5, atol=1e-4)  # batch composition: float order
        assert torch.equal(k.decode_image(_images()), k(ll_subband(_images())))
        assert torch.equal(k.bits(_images()), (k(ll) > 0).float())


def test_either_flip_negates_it_and_the_half_turn_keeps_it(decoder):
    ll = ll_subband(_images())
    k = KleinReadout(decoder)
    with torch.no_grad():
        base = k(ll)
        assert torch.allclose(k(ll.flip(-1)), -base, atol=1e-5)
        assert torch.allclose(k(ll.flip(-2)), -base, atol=1e-5)
        assert torch.allclose(k(ll.flip(-1).flip(-2)), base, atol=1e-5)
    # so on a population closed under a flip, every bit is 1 for exactly half of it, whatever the decoder leans to
    biased = KleinReadout(lambda x: decoder(x) + 50.0)  # a decoder that reads every bit as 1
    with torch.no_grad():
        pop = torch.cat([ll, ll.flip(-1)])
        assert torch.equal(biased(pop) > 0, k(pop) > 0)  # the lean cancels exactly
        ones = (k(pop) > 0).float().mean(dim=0)
    assert torch.equal(ones, torch.full((32,), 0.5))


def test_a_mark_embedded_for_it_is_read_through_it_and_not_directly(decoder):
    img = _images(1, 96, 80)[0]
    klein = KleinReadout(decoder)
    cfg = gsw.ImageEmbedConfig(steps=40, attack_every=0, psnr=32.0)
    res = gsw.embed_image(img, "key:studio", config=cfg, decoder=klein, progress=False)
    assert res.bit_accuracy == 1.0 and abs(res.psnr - 32.0) < 0.3  # read through the decoder it was embedded for
    assert torch.equal(gsw.extract(res.image, num_bits=32, decoder=klein).bits[0], message_from_key("studio", 32))
    assert gsw.verify([res.image], "key:studio", num_bits=32, decoder=klein).detected()


def test_it_is_another_decoder_for_the_registry_and_the_null_models(decoder):
    from gsw.decoder.null import decoder_fingerprint
    from gsw.decoder.zoo import load_decoder
    from gsw.mark.evidence import resolve_null_model

    klein = KleinReadout(decoder)
    assert decoder_fingerprint(klein) != decoder_fingerprint(decoder)  # marks made through it are told apart
    # the direct readout's null model is not used for it: it gets the one calibrated through it, where one ships
    # (32 and 64 bits), else the fair coin (48 bits)
    model, label = resolve_null_model(32, klein, None, False)
    direct, direct_label = resolve_null_model(32, decoder, None, False)
    assert label == direct_label == "calibrated" and model is not direct
    assert model.decoder_fingerprint == decoder_fingerprint(klein) and model.calibration["images"] > 0
    klein64 = KleinReadout(load_decoder(64))
    model64, label64 = resolve_null_model(64, klein64, None, False)
    assert label64 == "calibrated" and model64.decoder_fingerprint == decoder_fingerprint(klein64)
    assert model64.num_bits == 64 and model64.calibration["images"] > 0
    assert resolve_null_model(48, KleinReadout(load_decoder(48)), None, False)[1] == "fair"
