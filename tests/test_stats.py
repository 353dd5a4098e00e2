"""gsw.stats: Poisson-binomial tails, combinations valid under dependence, binomial intervals."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from gsw.stats import (beta_quantile, binomial_p_value, bonferroni_p_value, clopper_pearson,
                       fisher_combined_p_value, hommel_combined_p_value, poisson_binomial_pmf,
                       poisson_binomial_sf, regularized_beta)


def _enumerated_tail(q: np.ndarray, x: int) -> float:
    total = 0.0
    for outcome in itertools.product((0, 1), repeat=len(q)):
        if sum(outcome) >= x:
            total += math.prod(qi if o else 1 - qi for qi, o in zip(q, outcome))
    return total


def test_poisson_binomial_matches_enumeration():
    rng = np.random.default_rng(0)
    for k in (1, 3, 7):
        q = rng.uniform(0.02, 0.98, k)
        for x in range(-1, k + 2):
            assert float(poisson_binomial_sf(q, x)) == pytest.approx(_enumerated_tail(q, x), rel=1e-12, abs=1e-300)
    pmf = poisson_binomial_pmf(rng.uniform(0, 1, (5, 9)))
    assert pmf.shape == (5, 10) and np.allclose(pmf.sum(-1), 1.0)


def test_poisson_binomial_equals_binomial_at_one_half():
    for k in (32, 48, 64):
        tails = poisson_binomial_sf(np.full(k, 0.5), np.arange(k + 1))
        exact = np.array([binomial_p_value(x, k) for x in range(k + 1)])
        assert np.allclose(tails, exact, rtol=1e-12, atol=0)
    # the far tail keeps its relative accuracy (2^-64 = 5.4e-20, no 1 - cdf cancellation)
    assert float(poisson_binomial_sf(np.full(64, 0.5), 64)) == pytest.approx(2.0**-64, rel=1e-12)
    assert float(poisson_binomial_sf(np.full(64, 0.5), 60)) == pytest.approx(binomial_p_value(60, 64), rel=1e-12)


def test_poisson_binomial_broadcasting_and_errors():
    q = np.array([[0.5] * 4, [0.9] * 4])
    out = poisson_binomial_sf(q, np.array([[4], [0]]))
    assert out.shape == (2, 2)
    assert out[0, 0] == pytest.approx(1 / 16) and out[1, 1] == 1.0
    with pytest.raises(ValueError, match="in \\[0, 1\\]"):
        poisson_binomial_sf([0.5, 1.5], 1)
    with pytest.raises(ValueError, match="integers"):
        poisson_binomial_sf([0.5, 0.5], 1.5)


def _rate(p: np.ndarray, level: float) -> float:
    return float((p <= level).mean())


def test_hommel_valid_for_identical_and_independent_frames():
    rng = np.random.default_rng(1)
    sets, n, level = 40000, 10, 1e-2
    identical = np.repeat(rng.uniform(size=(sets, 1)), n, axis=1)  # perfectly correlated frames
    independent = rng.uniform(size=(sets, n))
    se = math.sqrt(level * (1 - level) / sets)
    assert _rate(hommel_combined_p_value(identical), level) <= level + 3 * se
    assert _rate(hommel_combined_p_value(independent), level) <= level + 3 * se
    # Fisher treats the n copies as independent evidence: far above the nominal rate
    fisher = np.array([fisher_combined_p_value(row) for row in identical[:4000]])
    assert _rate(fisher, level) > 5 * level


def test_hommel_values():
    harmonic = sum(1 / i for i in range(1, 11))
    assert float(hommel_combined_p_value([1e-3] * 10)) == pytest.approx(harmonic * 1e-3)
    assert float(hommel_combined_p_value([1e-4] + [1.0] * 9)) == pytest.approx(10 * harmonic * 1e-4)
    assert float(hommel_combined_p_value([0.3])) == pytest.approx(0.3)
    assert hommel_combined_p_value(np.full((3, 4), 0.9), axis=1).shape == (3,)
    with pytest.raises(ValueError, match="no p-values"):
        hommel_combined_p_value([])
    with pytest.raises(ValueError, match="in \\[0, 1\\]"):
        hommel_combined_p_value([0.1, 2.0])


def test_bonferroni():
    assert float(bonferroni_p_value([0.01, 0.5, 0.2])) == pytest.approx(0.03)
    assert float(bonferroni_p_value([0.6, 0.9])) == 1.0
    assert bonferroni_p_value(np.full((2, 5), 0.01), axis=0).shape == (5,)


def test_beta_and_clopper_pearson():
    # P(Bin(n, p) >= j) = I_p(j, n - j + 1)
    n, p = 20, 0.3
    for j in (1, 5, 12):
        exact = sum(math.comb(n, i) * p**i * (1 - p) ** (n - i) for i in range(j, n + 1))
        assert regularized_beta(j, n - j + 1, p) == pytest.approx(exact, rel=1e-10)
    assert beta_quantile(0.5, 2.0, 2.0) == pytest.approx(0.5, abs=1e-9)
    lo, hi = clopper_pearson(0, 10000)
    assert lo == 0.0 and hi == pytest.approx(1 - 0.025 ** (1 / 10000), rel=1e-8)
    lo, hi = clopper_pearson(5, 100)
    assert regularized_beta(5, 96, lo) == pytest.approx(0.025, abs=1e-9)  # P(X >= 5 | lo) = 2.5 %
    assert 1 - regularized_beta(6, 95, hi) == pytest.approx(0.025, abs=1e-9)  # P(X <= 5 | hi) = 2.5 %
    with pytest.raises(ValueError, match="successes"):
        clopper_pearson(3, 2)


def test_weighted_bonferroni_values_and_validity():
    assert float(bonferroni_p_value([0.01, 0.5], weights=[0.5, 0.5])) == pytest.approx(0.02)
    assert float(bonferroni_p_value([0.01, 0.002], weights=[0.9, 0.1])) == pytest.approx(0.01 / 0.9)
    assert float(bonferroni_p_value([0.01, 0.5, 0.2], weights=[1 / 3] * 3)) == pytest.approx(
        float(bonferroni_p_value([0.01, 0.5, 0.2])))
    assert float(bonferroni_p_value([1e-9, 0.5], weights=[0.0, 1.0])) == 0.5  # weight 0: never chosen
    assert bonferroni_p_value(np.full((5, 2), 0.01), axis=0, weights=np.full((5, 1), 0.2)).shape == (2,)
    with pytest.raises(ValueError, match="sum to at most 1"):
        bonferroni_p_value([0.1, 0.2], weights=[0.6, 0.6])
    with pytest.raises(ValueError, match=">= 0"):
        bonferroni_p_value([0.1, 0.2], weights=[-0.1, 0.5])
    # weights chosen from data independent of the p-values (like the decoder's confidence on a random key)
    rng = np.random.default_rng(2)
    trials, m, level = 40000, 5, 1e-2
    p = rng.uniform(size=(trials, m))
    w = np.full((trials, m), 0.1)
    w[np.arange(trials), rng.integers(0, m, trials)] += 0.5
    se = math.sqrt(level * (1 - level) / trials)
    assert _rate(bonferroni_p_value(p, weights=w), level) <= level + 3 * se


# ------------------------------------------------------------------------- the exact randomization test


def _enumerated_weighted_sums(w: np.ndarray) -> np.ndarray:
    """sum_i w_i B_i for every one of the 2^k outcomes of k fair bits."""
    k = len(w)
    outcomes = (np.arange(2**k)[:, None] >> np.arange(k)[None, :]) & 1
    return outcomes @ w


def test_weighted_sign_tail_matches_enumeration():
    from gsw.stats import weighted_sign_sf, weighted_sign_tail

    rng = np.random.default_rng(1)
    for k in (1, 5, 11, 16):
        for w in (np.ones(k, dtype=int), np.arange(1, k + 1), rng.integers(0, 25, k)):
            tail = weighted_sign_tail(w)
            assert tail.shape == (int(w.sum()) + 2,) and tail[0] == 1.0 and tail[-1] == 0.0
            sums = np.sort(_enumerated_weighted_sums(w))
            s = np.arange(-1, int(w.sum()) + 3)
            expected = 1.0 - np.searchsorted(sums, s, side="left") / len(sums)  # P(sum >= s), exact in float64
            assert np.array_equal(weighted_sign_sf(w, s), expected)
    # unit weights: the fair-coin binomial tail; rows with permuted weights share their table
    assert weighted_sign_sf(np.ones(32, int), 30) == pytest.approx(binomial_p_value(30, 32), rel=1e-14)
    rows = np.stack([rng.permutation(np.arange(1, 21)) for _ in range(3)] + [rng.integers(0, 9, 20)])
    tails = weighted_sign_tail(rows)
    assert tails.shape == (4, 212) and np.array_equal(tails[0], tails[2])
    obs = rng.integers(0, 211, (4, 6))
    assert np.array_equal(weighted_sign_sf(rows, obs), np.take_along_axis(tails, obs, axis=1))


def test_weighted_sign_tail_cache_is_invisible():
    """Rows are cached by their sorted weights: the same table whatever was computed before, never shared."""
    from gsw.stats import weighted_sign_tail

    ranks = np.stack([np.random.default_rng(i).permutation(np.arange(1, 33)) for i in range(3)])
    first = weighted_sign_tail(ranks)
    again = weighted_sign_tail(ranks[::-1])
    assert np.array_equal(first, again[::-1]) and np.array_equal(first[0], first[2])
    first[0, 1] = 7.0  # the caller's copy
    assert weighted_sign_tail(ranks[0])[1] != 7.0


def test_weighted_sign_tail_matches_simulation_and_keeps_tiny_tails():
    from gsw.stats import weighted_sign_sf

    rng = np.random.default_rng(2)
    w = rng.integers(0, 30, 48)
    sums = (rng.integers(0, 2, (200_000, 48)) * w).sum(1)
    for s in (int(np.quantile(sums, q)) for q in (0.5, 0.9, 0.99)):
        expected = float((sums >= s).mean())
        assert float(weighted_sign_sf(w, s)) == pytest.approx(expected, abs=4 * (expected / 200_000) ** 0.5 + 1e-4)
    ranks = np.arange(1, 65)
    assert float(weighted_sign_sf(ranks, int(ranks.sum()))) == 2.0**-64  # all 64 bits: exactly 2^-64
    assert float(weighted_sign_sf(ranks, int(ranks.sum()) - 1)) == 2 * 2.0**-64  # all, or all but bit 1


def test_weighted_sign_errors():
    from gsw.stats import weighted_sign_sf, weighted_sign_tail

    for bad, match in ((np.zeros(0), "shape"), (np.array([1.5, 2.0]), "integers"), (np.array([1, -1]), ">= 0"),
                       (np.array([np.nan, 1.0]), "integers")):
        with pytest.raises(ValueError, match=match):
            weighted_sign_tail(bad)
    with pytest.raises(ValueError, match="one row per row"):
        weighted_sign_sf(np.ones((3, 4), int), np.zeros((2, 5), int))
    with pytest.raises(ValueError, match="integers"):
        weighted_sign_sf(np.ones(4, int), 1.5)


def test_check_origin():
    from gsw.stats import ORIGINS, check_origin

    assert [check_origin(o) for o in ORIGINS] == ["random", "chosen"]
    with pytest.raises(ValueError, match="origin must be one of random, chosen, got 'fixed'"):
        check_origin("fixed")
