"""gsw.decoder.null: the per-decoder null model, its conservative p-values, files and decoder checks."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from gsw.decoder.null import (NullModel, NullModelError, Stratum, decoder_fingerprint, fit_null_model,
                              is_holdout, load_null_model, null_path)
from gsw.decoder.zoo import AVAILABLE_BITS, WEIGHTS_DIR, WatermarkDecoder, load_decoder
from gsw.stats import binomial_p_value, poisson_binomial_sf


def _stratum(p1, se=0.0, corr=None, direction="down"):
    k = len(p1)
    return Stratum(f"test/{direction}", direction, 100, 100, np.asarray(p1, float), np.full(k, se),
                   np.eye(k) if corr is None else corr)


def _model(p1, se=0.0, corr=None):
    return NullModel(len(p1), [_stratum(p1, se, corr)])


def test_fair_model_gives_binomial_p_values():
    null = NullModel.fair(32)
    table = null.tail_table(np.zeros(32, dtype=int))
    assert np.allclose(table[:33], [binomial_p_value(x, 32) for x in range(33)], rtol=1e-12)
    assert table[33] == 0.0
    bits = np.array([[0] * 32, [1] * 32])
    assert np.allclose(null.p_values(bits, np.zeros(32)), [2.0**-32, 1.0])


def test_biased_bits_raise_aligned_p_values_and_never_go_below_the_fair_coin():
    k = 32
    p1 = np.where(np.arange(k) % 2 == 0, 0.7, 0.4)
    null = _model(p1)
    aligned = (p1 > 0.5).astype(int)  # the message the biases favour
    table = null.tail_table(aligned)
    plug_in = poisson_binomial_sf(np.where(aligned == 1, p1, 1 - p1), np.arange(k + 1))
    fair = np.array([binomial_p_value(x, k) for x in range(k + 1)])
    assert np.allclose(table[: k + 1], np.maximum(fair, plug_in), rtol=1e-9)
    assert table[28] > 50 * fair[28]
    assert np.all(null.tail_table(1 - aligned)[: k + 1] >= fair * (1 - 1e-12))  # anti-aligned: the fair floor


def test_estimation_error_makes_the_bound_conservative():
    k = 32
    p1 = np.full(k, 0.55)
    exact, uncertain = _model(p1), _model(p1, se=0.03)
    m = np.ones(k, dtype=int)
    assert np.all(uncertain.tail_table(m) >= exact.tail_table(m) * (1 - 1e-12))
    assert uncertain.tail_table(m)[30] > 1.5 * exact.tail_table(m)[30]


def test_fitted_model_controls_false_positives_for_the_worst_message():
    """Simulated decoder with strong per-bit biases: fit on 300 unmarked 'images', then count unmarked
    images that pass 1e-2 for the message aligned with the biases (the fair coin fails here)."""
    rng = np.random.default_rng(0)
    k, level = 32, 1e-2
    true_p1 = rng.uniform(0.3, 0.7, k)
    calib = (rng.uniform(size=(300, k)) < true_p1).astype(int)
    records = [{"name": f"img{i}", "kind": "photo", "factor": 1.0, "bits": b.tolist()} for i, b in enumerate(calib)]
    null = fit_null_model(records, k, draws=500)
    assert null.calibration["images"] == 300 and null.calibration["strata"]["photo/down"]["images"] == 300
    worst = (true_p1 > 0.5).astype(int)
    test = (rng.uniform(size=(50000, k)) < true_p1).astype(int)
    new_rate = float((null.p_values(test, worst) <= level).mean())
    fair_rate = float((NullModel.fair(k).p_values(test, worst) <= level).mean())
    assert fair_rate > 3 * level
    assert new_rate <= level


def test_json_round_trip_and_errors(tmp_path):
    null = _model(np.linspace(0.3, 0.7, 8), se=0.01)
    null.calibration = {"images": 3}
    path = null.save(tmp_path / "null.json")
    back = NullModel.load(path)
    assert back.num_bits == 8 and len(back.strata) == 1
    assert np.allclose(back.strata[0].p1, null.strata[0].p1, atol=1e-5) and np.allclose(back.strata[0].p1_se, 0.01)
    assert back.calibration == {"images": 3}
    m = np.array([1, 0, 1, 1, 0, 0, 1, 0])
    assert np.allclose(back.tail_table(m), null.tail_table(m), rtol=1e-3)
    d = json.loads(path.read_text())
    del d["strata"][0]["p1"]
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(NullModelError, match="missing field 'p1'"):
        NullModel.load(tmp_path / "bad.json")
    d = null.to_dict()
    d["strata"][0]["p1"] = [0.5] * 7
    with pytest.raises(NullModelError, match="stratum 'test/down' field 'p1'"):
        NullModel.from_dict(d)
    d["format"] = "something else"
    with pytest.raises(NullModelError, match="not a gsw null model"):
        NullModel.from_dict(d)
    with pytest.raises(NullModelError, match="not found"):
        NullModel.load(tmp_path / "missing.json")
    with pytest.raises(NullModelError, match="8-bit decoder, 32 bits"):
        load_null_model(32, path)


def test_wrong_message_or_bits():
    null = NullModel.fair(32)
    with pytest.raises(ValueError, match=r"expected \[\.\.\., 32\]"):
        null.tail_table(np.ones(31))
    with pytest.raises(ValueError, match="bits"):
        null.p_values(np.full((2, 32), 2), np.ones(32))


def test_decoder_check():
    torch.manual_seed(0)
    a, b = WatermarkDecoder(8, num_blocks=1, channels=4), WatermarkDecoder(8, num_blocks=1, channels=4)
    records = [{"name": "x", "kind": "photo", "factor": 1.0, "bits": [0, 1] * 4},
               {"name": "y", "kind": "photo", "factor": 1.0, "bits": [1, 1] * 4}]
    null = fit_null_model(records, 8, decoder=a, min_images=1)
    assert null.decoder_fingerprint == decoder_fingerprint(a)
    null.check_decoder(a)
    with pytest.raises(NullModelError, match="not for this decoder"):
        null.check_decoder(b)
    with pytest.raises(NullModelError, match="8-bit decoder given with a 32-bit"):
        null.check_decoder(WatermarkDecoder(32, num_blocks=1, channels=4))


def test_shipped_null_models_match_the_shipped_decoders(tmp_path):
    for k in AVAILABLE_BITS:
        null = load_null_model(k)
        assert null.num_bits == k and null.calibration["images"] > 100
        null.check_decoder(load_decoder(k))
    # a manifest naming other weights -> the shipped null model is refused
    for name in ("manifest.json", "null_k32.json"):
        shutil.copy(WEIGHTS_DIR / name, tmp_path / name)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    manifest["files"]["hidden_k32.pt"]["sha256"] = "0" * 64
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(NullModelError, match="recalibrate"):
        load_null_model(32, weights_dir=tmp_path)
    assert null_path(32, tmp_path) == tmp_path / "null_k32.json"


def test_holdout_split_is_fixed_and_about_half():
    names = [f"unmarked/sun80/img_{i:03d}.jpg" for i in range(400)]
    held = [is_holdout(n) for n in names]
    assert held == [is_holdout(n) for n in names]
    assert 0.4 < np.mean(held) < 0.6


def test_null_model_imports_without_the_compiled_extension():
    import subprocess
    import sys

    code = ("import importlib.abc, sys\n"
            "class _Block(importlib.abc.MetaPathFinder):\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name == 'gsw._C':\n"
            "            raise ImportError('blocked')\n"
            "sys.meta_path.insert(0, _Block())\n"
            "import gsw.decoder.null\nassert 'gsw._C' not in sys.modules\nprint('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_positive_bit_correlation_widens_the_tail_and_negative_does_not_narrow_it():
    k = 32
    p1 = np.full(k, 0.5)
    m = np.ones(k, dtype=int)
    pos = np.full((k, k), 0.1)
    np.fill_diagonal(pos, 1.0)
    neg = np.full((k, k), -0.02)
    np.fill_diagonal(neg, 1.0)
    plain, wide, narrow = _model(p1), _model(p1, corr=pos), _model(p1, corr=neg)
    assert wide.tail_table(m)[29] > 100 * plain.tail_table(m)[29]
    assert np.allclose(narrow.tail_table(m), plain.tail_table(m))
    # the same correlations with a message that flips half the bits: the matches decorrelate
    flipped = np.array([1, 0] * (k // 2))
    assert wide.tail_table(flipped)[29] < wide.tail_table(m)[29]


def test_strata_envelope_covers_each_kind_and_reading_direction():
    """Two kinds of content with opposite biases: the model must hold for the worst message of each."""
    rng = np.random.default_rng(2)
    k, level = 32, 1e-2
    kinds = {"a": rng.uniform(0.3, 0.7, k), "b": rng.uniform(0.3, 0.7, k)}
    records = [{"name": f"{kd}{i}", "kind": kd, "factor": 1.0, "bits": (rng.uniform(size=k) < p).astype(int).tolist()}
               for kd, p in kinds.items() for i in range(300)]
    records += [{"name": "c0", "kind": "c", "factor": 1.0, "bits": [0] * k}]  # too few images: left out
    null = fit_null_model(records, k, draws=300)
    assert sorted(s.name for s in null.strata) == ["a/down", "b/down"]
    assert null.calibration["left_out_readings"] == {"c/down": 1}
    for p in kinds.values():
        worst = (p > 0.5).astype(int)
        test = (rng.uniform(size=(20000, k)) < p).astype(int)
        assert float((null.p_values(test, worst) <= level).mean()) <= level
    up = NullModel(k, [_stratum(np.full(k, 0.5)), _stratum(np.full(k, 0.8), direction="up")])
    bits = np.ones((2, k), dtype=int)
    bits[:, :4] = 0
    p_down, p_up = up.p_values(bits, np.ones(k), factors=[1.0, 2.0])
    assert p_down == pytest.approx(binomial_p_value(28, k)) and p_up > 100 * p_down
