"""Whitening of pre-trained decoders (gsw.decoder.pretrain.whiten)."""

import pytest
import torch

from gsw.decoder import load_decoder
from gsw.decoder.hidden import HiddenDecoder
from gsw.decoder.pretrain.whiten import fit_whitening_multi, shipped_whitening


def test_fit_whitening_multi_counts_samples_and_caps_crop_sizes():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    images = [(torch.rand(3, 48, 64, generator=g) * 255).to(torch.uint8) for _ in range(3)]
    bank = torch.stack(images)
    decs = [HiddenDecoder(4, 2, 8), HiddenDecoder(6, 2, 8)]
    layers, n = fit_whitening_multi(decs, images, bank, num_crops=40, crop_sizes=(32, 128))  # 128 > 48: capped
    assert n == 2 * 3 + 40
    assert [w.weight.shape for w in layers] == [(4, 4), (6, 6)]
    again, _ = fit_whitening_multi(decs, images, bank, num_crops=40, crop_sizes=(32, 128))
    assert torch.equal(again[1].weight, layers[1].weight)  # seeded crops: the same fit
    other, _ = fit_whitening_multi(decs, images, bank, num_crops=40, crop_sizes=(32, 128), seed=2)
    assert not torch.equal(other[1].weight, layers[1].weight)


def test_shipped_whitening_only_for_the_shipped_decoder():
    shipped = load_decoder(32)
    w = shipped_whitening(shipped.decoder, 32)
    assert torch.equal(w.weight, shipped.whitening.weight)
    other = HiddenDecoder(32, 8, 64, "standardize")
    with pytest.raises(ValueError, match="32-bit decoder is not the shipped one"):
        shipped_whitening(other, 32)
