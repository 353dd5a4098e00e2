"""gsw.mark.randomization: the exact randomization test for random messages (weights, selection, pooling)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gsw.mark.evidence import score_messages
from gsw.mark.randomization import (MAGNITUDE_CLIP, MAGNITUDE_LEVELS, WEIGHTINGS, bit_weights, choose_reading,
                                    exact_p_values, logit_scale, pooled_logits)
from gsw.mark.scales import Reading
from gsw.stats import binomial_p_value, weighted_sign_sf


def test_bit_weights():
    logits = torch.tensor([[0.5, -2.0, 0.5, 0.1], [0.0, 0.0, 0.0, 0.0]])
    assert bit_weights(logits, "rank").tolist() == [[2, 4, 3, 1], [1, 2, 3, 4]]  # ties broken by index
    assert bit_weights(logits, "sign").tolist() == [[1] * 4] * 2
    mag = bit_weights(torch.tensor([1.0, -2.0, 1.0, 0.1, 10.0]), "magnitude")  # median |logit| 1
    assert mag.tolist() == [MAGNITUDE_LEVELS, 2 * MAGNITUDE_LEVELS, MAGNITUDE_LEVELS, round(0.1 * MAGNITUDE_LEVELS),
                            round(MAGNITUDE_CLIP * MAGNITUDE_LEVELS)]
    assert logit_scale(np.zeros((2, 3))).tolist() == [1.0, 1.0]
    for w in WEIGHTINGS:  # invariant to the logits' scale (frames read at other sizes)
        assert np.array_equal(bit_weights(3.0 * logits[:1], w), bit_weights(logits[:1], w))


def test_p_values_use_weights_from_the_logits_only():
    gen = np.random.default_rng(0)
    logits = gen.standard_normal((5, 32))
    msgs = gen.integers(0, 2, (7, 32))
    for w in WEIGHTINGS:
        p, matches = exact_p_values(logits, np.concatenate([msgs, 1 - msgs]), w)
        weights = bit_weights(logits, w)
        bits = logits > 0
        for j, m in enumerate(msgs):
            matched = ((bits == m) * weights).sum(1)
            assert np.array_equal(p[:, j], weighted_sign_sf(weights, matched))  # the same weights for every message
            assert np.array_equal(matches[:, j] + matches[:, j + 7], [32] * 5)
    p, matches = exact_p_values(logits, msgs, "sign")
    assert p[0, 0] == pytest.approx(binomial_p_value(int(matches[0, 0]), 32), rel=1e-12)


def test_selection_never_looks_at_the_message():
    """The most confident reading is tested even when another one matches the message better."""
    gen = torch.Generator().manual_seed(1)
    msg = torch.randint(0, 2, (32,), generator=gen)
    good = 0.5 * (2 * msg.float() - 1)  # reads the message, weakly
    noise = 3.0 * torch.randn(32, generator=gen)  # confident noise
    r = Reading([1.0, 0.5], [(64, 64), (32, 32)], torch.stack([noise, good]))
    others = torch.randint(0, 2, (50, 32), generator=gen)
    sc = score_messages([r], np.concatenate([msg[None].numpy(), others.numpy()]).astype(np.int8))
    assert choose_reading(r.confidence) == 0 and sc.chosen.tolist() == [[0] * 51]
    assert sc.p_values[0, 0] == exact_p_values(noise, msg[None].numpy())[0][0, 0]
    with pytest.raises(ValueError, match="shape"):
        choose_reading(np.zeros((2, 2)))


def test_identical_frames_pool_to_the_single_frame_p_value():
    gen = torch.Generator().manual_seed(2)
    logits = torch.randn(1, 32, generator=gen)
    msgs = torch.randint(0, 2, (20, 32), generator=gen).numpy().astype(np.int8)
    one = score_messages([Reading([1.0], [(64, 64)], logits)], msgs)
    forty = score_messages([Reading([1.0], [(64, 64)], logits)] * 40, msgs)
    assert np.array_equal(forty.combined, one.combined) and np.array_equal(forty.p_values[0], one.p_values[0])
    assert np.allclose(pooled_logits(torch.cat([logits, 2 * logits])), 2 * logits[0] / logit_scale(logits)[0])


@pytest.mark.parametrize("weighting", WEIGHTINGS)
def test_size_is_nominal_for_strongly_correlated_biased_frames(weighting):
    """Unmarked 'videos': 40 nearly identical frames of a decoder whose bits are heavily biased; random
    messages. The pooled test's false-positive rate is the nominal one within simulation error."""
    gen = np.random.default_rng(3)
    trials, per_trial, k = 200, 50, 32
    bias = 1.5 * gen.standard_normal(k)  # the decoder's per-bit bias on unmarked content
    p = []
    for _ in range(trials):
        base = bias + gen.standard_normal(k)
        frames = [Reading([1.0], [(64, 64)], torch.from_numpy(base + 0.05 * gen.standard_normal((1, k))).float())
                  for _ in range(40)]
        p.append(score_messages(frames, gen.integers(0, 2, (per_trial, k)).astype(np.int8),
                                weighting=weighting).combined)
    p = np.concatenate(p)
    n = p.size
    for level in (0.05, 0.01):
        size = float(np.mean(p <= level))
        assert abs(size - level) <= 4 * (level * (1 - level) / n) ** 0.5 + (0.0 if weighting != "sign" else level)
        if weighting != "sign":  # a continuous statistic reaches the nominal rate, not only stays below it
            assert size >= level - 4 * (level * (1 - level) / n) ** 0.5


def test_errors():
    with pytest.raises(ValueError, match="weighting must be one of rank, sign, magnitude"):
        bit_weights(np.ones(4), "ranks")
    with pytest.raises(ValueError, match="finite"):
        bit_weights(np.array([np.inf, 1.0]))
    with pytest.raises(ValueError, match=r"expected \[M, 4\]"):
        exact_p_values(np.ones(4), np.ones((2, 5)))
    with pytest.raises(ValueError, match="0 or 1"):
        exact_p_values(np.ones(4), 2 * np.ones((2, 4)))
    with pytest.raises(ValueError, match=r"\[F, k\]"):
        pooled_logits(np.ones(4))
    with pytest.raises(ValueError, match="returned 4 bits, num_bits=5"):
        score_messages([Reading([1.0], [(8, 8)], torch.ones(1, 4))], np.ones((1, 5), dtype=np.int8))
    with pytest.raises(ValueError, match="null model"):
        score_messages([Reading([1.0], [(8, 8)], torch.ones(1, 4))], np.ones((1, 4), dtype=np.int8), origin="chosen")
    with pytest.raises(ValueError, match="origin must be one of"):
        score_messages([Reading([1.0], [(8, 8)], torch.ones(1, 4))], np.ones((1, 4), dtype=np.int8), origin="x")
