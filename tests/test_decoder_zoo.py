"""Shipped decoder weights: loading, integrity checks, user weights, unbiasedness on val photos."""

import json
import shutil

import pytest
from helpers import SHARED_DATA, require
import torch

from gsw.decoder import AVAILABLE_BITS, HiddenDecoder, WeightsError, WhiteningLayer, load_decoder, save_decoder
from gsw.decoder.zoo import MANIFEST_HEADER, WEIGHTS_DIR, record_in_manifest, sha256_file

DATA = SHARED_DATA


@pytest.mark.parametrize("bits", AVAILABLE_BITS)
def test_shipped_decoders_load_and_decode(bits):
    dec = load_decoder(bits)
    assert not dec.training and not any(p.requires_grad for p in dec.parameters())
    x = torch.rand(2, 3, 96, 80)
    logits = dec.decode_image(x)
    assert logits.shape == (2, bits) and torch.isfinite(logits).all()
    assert torch.equal(dec.bits(x), (logits > 0).float())
    assert (WEIGHTS_DIR / f"hidden_k{bits}.pt").stat().st_size < 4_000_000


def _copy_weights(tmp_path):
    d = tmp_path / "weights"
    shutil.copytree(WEIGHTS_DIR, d)
    return d


def test_corrupt_file_is_rejected(tmp_path):
    d = _copy_weights(tmp_path)
    f = d / "hidden_k32.pt"
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0xFF
    f.write_bytes(bytes(data))
    with pytest.raises(WeightsError, match="corrupt"):
        load_decoder(32, weights_dir=d)


def test_missing_file_and_manifest(tmp_path):
    d = _copy_weights(tmp_path)
    (d / "hidden_k48.pt").unlink()
    with pytest.raises(WeightsError, match="not found"):
        load_decoder(48, weights_dir=d)
    (d / "manifest.json").unlink()
    with pytest.raises(WeightsError, match="manifest"):
        load_decoder(32, weights_dir=d)
    with pytest.raises(WeightsError, match="no shipped decoder"):
        load_decoder(16)


def test_user_weights_roundtrip_and_checks(tmp_path):
    torch.manual_seed(0)
    dec, wl = HiddenDecoder(16, num_blocks=3, channels=24, input_norm="center").eval(), WhiteningLayer(16).fit(
        torch.randn(200, 16))
    path = tmp_path / "mine.pt"
    sha = save_decoder(dec, wl, path)
    assert sha == sha256_file(path)
    model = load_decoder(16, path, sha256=sha)
    assert model.decoder.input_norm == "center" and len(model.decoder.layers) == 4  # architecture kept
    ll = torch.rand(2, 3, 8, 8)
    with torch.no_grad():
        assert torch.allclose(model(ll), wl(dec(ll)), atol=1e-5)
    with pytest.raises(WeightsError, match="corrupt"):
        load_decoder(16, path, sha256="0" * 64)
    with pytest.raises(WeightsError, match="16-bit"):
        load_decoder(32, path)
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(WeightsError, match="cannot read"):
        load_decoder(16, tmp_path / "junk.pt")


def test_exporting_one_bit_length_keeps_the_others_in_the_manifest(tmp_path):
    d = _copy_weights(tmp_path)
    before = json.loads((d / "manifest.json").read_text())
    assert {n: before[n] for n in MANIFEST_HEADER} == MANIFEST_HEADER  # the shipped header is the writer's
    torch.manual_seed(0)
    dec, wl = HiddenDecoder(32, num_blocks=2, channels=8).eval(), WhiteningLayer(32).fit(torch.randn(100, 32))
    save_decoder(dec, wl, d / "hidden_k32.pt")  # a new 32-bit decoder, then its entry only
    man = record_in_manifest(d / "hidden_k32.pt", {"device": "test"})
    assert man == json.loads((d / "manifest.json").read_text())
    assert list(man["files"]) == [f"hidden_k{k}.pt" for k in AVAILABLE_BITS]
    assert man["files"]["hidden_k32.pt"]["device"] == "test"
    assert man["files"]["hidden_k32.pt"]["sha256"] == sha256_file(d / "hidden_k32.pt")
    assert man["files"]["hidden_k48.pt"] == before["files"]["hidden_k48.pt"]
    with torch.no_grad():
        ll = torch.rand(1, 3, 8, 8)
        assert torch.allclose(load_decoder(32, weights_dir=d)(ll), wl(dec(ll)), atol=1e-5)  # the new one
    load_decoder(48, weights_dir=d)  # the others still pass their integrity check
    load_decoder(64, weights_dir=d)


def test_manifest_matches_files():
    man = json.loads((WEIGHTS_DIR / "manifest.json").read_text())
    for bits in AVAILABLE_BITS:
        entry = man["files"][f"hidden_k{bits}.pt"]
        assert entry["num_bits"] == bits
        assert entry["sha256"] == sha256_file(WEIGHTS_DIR / f"hidden_k{bits}.pt")


def test_unmarked_val_photos_decode_to_chance():
    val = require(DATA / "bsds500" / "val")
    from gsw.decoder.pretrain.evaluation import unbiasedness
    from gsw.decoder.pretrain.data import load_images

    images = [img[:, :128, :128] for img in load_images(val, limit=20)]
    res = unbiasedness(load_decoder(32), images, 32, num_messages=200, seed=0)
    assert abs(res["mean_bit_acc"] - 0.5) < 0.02
    assert res["false_positives"] == 0


def test_false_positive_threshold():
    from gsw.stats import binomial_p_value, false_positive_threshold

    assert [false_positive_threshold(k) for k in (32, 48, 64)] == [30, 41, 51]  # the thresholds
    assert binomial_p_value(30, 32) <= 1e-6 < binomial_p_value(29, 32)
    assert false_positive_threshold(8) == 9  # no count of 8 bits reaches 1e-6


def test_fair_max_dev_matches_the_binomial_floor():
    from gsw.decoder.pretrain.evaluation import fair_max_dev

    # one fair bit over n images: median |P(1) - 0.5| = 0.6745 * 0.5 / sqrt(n) (half-normal median)
    assert abs(fair_max_dev(400, 1) - 0.6745 * 0.5 / 20) < 0.006
    assert fair_max_dev(100, 64) > fair_max_dev(100, 32) > fair_max_dev(100, 1)  # more bits, larger max
    assert fair_max_dev(10_000, 32) < fair_max_dev(100, 32) / 5  # shrinks like 1 / sqrt(n)


def test_fair_max_dev_with_a_fitted_median_and_its_p_value():
    from gsw.decoder.pretrain.evaluation import fair_max_dev, max_dev_p_value

    # a median fitted on n_fit images adds its own error: one bit's P(1) then has variance
    # 0.25 / n + 0.25 / n_fit (n = n_fit = 400: sd 0.0354, half-normal median 0.6745 sd)
    assert abs(fair_max_dev(400, 1, n_fit=400) - 0.6745 * 0.5 * (2 / 400) ** 0.5) < 0.006
    assert fair_max_dev(100, 64, n_fit=200) > fair_max_dev(100, 64)
    assert abs(fair_max_dev(100, 64, n_fit=10**7) - fair_max_dev(100, 64)) <= 0.01  # exact median in the limit
    assert max_dev_p_value(0.0, 100, 32) == 1.0  # every evaluation deviates at least 0
    assert max_dev_p_value(0.5, 100, 32) < 1e-3  # a stuck bit is no sampling accident
    p = [max_dev_p_value(d, 100, 32, n_fit=200) for d in (0.1, 0.15, 0.2)]
    assert p[0] > p[1] > p[2]


def test_shipped_decoders_keep_the_trained_input_normalisation():
    # the exported architecture must be the trained one (an export once dropped input_norm="standardize")
    for k in AVAILABLE_BITS:
        blob = torch.load(WEIGHTS_DIR / f"hidden_k{k}.pt", map_location="cpu", weights_only=False)
        assert load_decoder(k).decoder.input_norm == blob["arch"]["input_norm"] != "none"
