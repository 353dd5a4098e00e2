"""Detection statistics: p-values of matching bits, their combination, the detection threshold.

Torch-free (``math`` and ``numpy`` only), shared by the embedder, the detector, the evaluation and the
decoder pre-training.

Two kinds of tail:

* :func:`binomial_p_value` -- the fair coin: exact when the message is uniformly random and drawn
  independently of the image (a key the image was not made with).
* :func:`weighted_sign_sf` -- the exact randomization (key) test on soft outputs: each bit carries an
  integer weight ``w_i >= 0`` that depends on the decoder's output only (not on the message), and the
  statistic is the total weight of the matching bits.  For a uniformly random message drawn independently
  of the image, the bits match independently with probability 1/2 *whatever* the image and the decoder
  (bias, correlated bits, correlated frames), so the tail ``P(sum_i w_i B_i >= s)`` with ``B_i`` iid
  Bernoulli(1/2) is the exact null distribution given the decoder's output; dynamic programme over the
  integer sums, in float64.  Unit weights give :func:`binomial_p_value`.
* :func:`poisson_binomial_sf` -- bit ``i`` matches with its own probability ``q_i`` (a decoder whose bits
  are biased on unmarked content, :mod:`gsw.decoder.null`); exact dynamic programme in float64, summed
  over the upper tail only (no ``1 - cdf`` cancellation), so tails down to ``1e-300`` keep their relative
  accuracy.

Combining several images of one scene (:func:`hommel_combined_p_value`) and the best of several readings
of one image (:func:`bonferroni_p_value`) use rules that hold under arbitrary dependence: near-duplicate
frames of an unmarked scene decode to nearly the same bits, so the independence behind
:func:`fisher_combined_p_value` does not hold for them.

Example:
    >>> false_positive_threshold(32), false_positive_threshold(48), false_positive_threshold(64)
    (30, 41, 51)
    >>> float(poisson_binomial_sf([0.5] * 32, 30)) == binomial_p_value(30, 32)
    True
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

#: The false-positive rate at which a copy counts as watermarked (``gsw verify``, ``Verdict.detected``).
DETECTION_FPR = 1e-6

#: Where a claimed message came from, which decides its test: ``"random"`` (drawn uniformly at random,
#: independently of any image: gsw's default messages, ``key:<secret>``; the exact randomization test,
#: :func:`weighted_sign_sf`) or ``"chosen"`` (picked by someone, e.g. a hex message typed by a user: it may
#: line up with a decoder's biases, so it is tested against the decoder's calibrated null model).
ORIGINS = ("random", "chosen")


def check_origin(origin: str) -> str:
    """``origin`` if it is one of :data:`ORIGINS`, else a ValueError naming them."""
    if origin not in ORIGINS:
        raise ValueError(f"message origin must be one of {', '.join(ORIGINS)}, got {origin!r}")
    return origin


def binomial_p_value(matches: int, num_bits: int) -> float:
    """P(X >= matches) for X ~ Binomial(num_bits, 1/2): the chance an unmarked image matches as well."""
    if not 0 <= matches <= num_bits:
        raise ValueError(f"matches={matches} outside 0..{num_bits}")
    return sum(math.comb(num_bits, i) for i in range(matches, num_bits + 1)) / 2.0**num_bits


def false_positive_threshold(k: int, fpr: float = DETECTION_FPR) -> int:
    """Smallest number of matching bits m with P(X >= m) <= fpr for an unmarked image (X ~ Bin(k, 1/2)).

    Returns ``k + 1`` (never reached) when even k of k matching bits is more likely than ``fpr``
    (k < 20 for 1e-6): such a message length cannot prove anything at that rate."""
    return next((m for m in range(k + 1) if binomial_p_value(m, k) <= fpr), k + 1)

def fisher_combined_p_value(p_values: Sequence[float]) -> float:
    """Fisher's method: combined p-value of independent tests (closed form for 2k degrees of freedom).

    Only valid for independent tests: near-duplicate frames of one scene are not (use
    :func:`hommel_combined_p_value`)."""
    ps = [max(float(p), 1e-300) for p in p_values]
    if not ps:
        raise ValueError("no p-values to combine")
    half = -sum(math.log(p) for p in ps)  # chi2 / 2 with 2k dof
    term, total = 1.0, 1.0
    for i in range(1, len(ps)):
        term *= half / i
        total += term
    return min(1.0, math.exp(-half) * total)


def bootstrap_ci95(values: Sequence[float], n: int = 10000, seed: int = 0) -> list[float]:
    """95 % percentile-bootstrap interval of the mean of ``values`` (e.g. per-photo accuracies)."""
    a = np.asarray(values, dtype=np.float64)
    boot = np.random.default_rng(seed).choice(a, (n, len(a))).mean(1)
    return [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))]


# ------------------------------------------------------------------------------- randomly signed sums


def _integer_weights(weights: ArrayLike) -> np.ndarray:
    w = np.asarray(weights)
    if w.ndim == 0 or w.shape[-1] == 0:
        raise ValueError(f"expected per-bit weights of shape [..., k] with k >= 1, got shape {w.shape}")
    if not np.issubdtype(w.dtype, np.integer):
        if not np.all(np.isfinite(w)) or not np.all(w == np.round(w)):
            raise ValueError("per-bit weights must be integers")
    w = w.astype(np.int64)
    if w.min() < 0:
        raise ValueError("per-bit weights must be >= 0")
    return w


def _integers(values: ArrayLike, what: str) -> np.ndarray:
    """``values`` as an integer array; a ValueError naming ``what`` when they are not whole numbers."""
    x = np.asarray(values)
    if not np.issubdtype(x.dtype, np.integer):
        if not np.all(x == np.round(x)):
            raise ValueError(f"{what} must hold integers")
        x = x.astype(np.int64)
    return x


def weighted_sign_tail(weights: ArrayLike) -> np.ndarray:
    """Exact tail of the total weight of the bits a uniformly random message matches.

    With ``B_i`` iid Bernoulli(1/2) (bit ``i`` of a random message agrees with the reading or not) and
    integer weights ``w_i >= 0``: entry ``s`` is ``P(sum_i w_i B_i >= s)``.  In terms of the signed sum
    ``T = sum_i w_i eps_i`` (``eps_i = 2 B_i - 1`` Rademacher, ``S = sum_i w_i``): ``P(T >= 2 s - S)``.
    Dynamic programme over the integer sums (``O(k S)`` per row; rows with the same multiset of weights
    are computed once, and kept for later calls: the default rank weights give every reading the same
    multiset); every entry is a sum of non-negative terms, so tails down to ``2^-k`` keep their
    relative accuracy.

    Args:
        weights: [..., k] non-negative integers.

    Returns:
        [..., S_max + 2] float64, ``S_max`` the largest row total: entry 0 is 1, entries above a row's
        own total are 0.
    """
    w = _integer_weights(weights)
    lead, k = w.shape[:-1], w.shape[-1]
    rows, inverse = np.unique(np.sort(w.reshape(-1, k), axis=1), axis=0, return_inverse=True)
    total = int(rows.sum(axis=1).max())
    tail = np.zeros((rows.shape[0], total + 2))
    for r, row in enumerate(rows):  # a row's entries above its own total stay 0
        own = _sorted_weights_tail(row.tobytes(), k)
        tail[r, :own.size] = own
    return tail[inverse.reshape(-1)].reshape(lead + (total + 2,))


@functools.lru_cache(maxsize=1024)
def _sorted_weights_tail(row: bytes, k: int) -> np.ndarray:
    """:func:`weighted_sign_tail` of one row of sorted int64 weights (given as bytes, so that it can be cached:
    rank weights are the same multiset for every reading), length ``total + 1``; read-only."""
    w = np.frombuffer(row, dtype=np.int64, count=k)
    total = int(w.sum())
    pmf = np.zeros(total + 1)
    pmf[0] = 1.0
    for wi in w.tolist():
        moved = np.zeros(total + 1)
        moved[wi:] = pmf[:total + 1 - wi]
        pmf = 0.5 * (pmf + moved)
    tail = np.minimum(np.cumsum(pmf[::-1])[::-1], 1.0)
    tail.flags.writeable = False
    return tail


def weighted_sign_sf(weights: ArrayLike, matched: ArrayLike) -> np.ndarray:
    """p-values of the exact randomization test: ``P(sum_i w_i B_i >= matched)`` (:func:`weighted_sign_tail`).

    Args:
        weights: [k] or [R, k] non-negative integer weights (one row per reading).
        matched: the observed total weight of the matching bits: any shape for 1-D ``weights``, else
            [R, ...] (row ``r`` tested with weights ``r``), e.g. [R, M] for M messages.

    Returns:
        float64 p-values of ``matched``'s shape (1 for ``matched <= 0``, 0 above the row's total).
    """
    table = weighted_sign_tail(weights)
    x = _integers(matched, "matched (a total of integer weights)")
    idx = np.clip(x, 0, table.shape[-1] - 1)
    if table.ndim == 1:
        return table[idx]
    lead = table.shape[:-1]
    if x.shape[: len(lead)] != lead:
        raise ValueError(f"matched has shape {list(x.shape)}; expected [{', '.join(map(str, lead))}, ...] "
                         "(one row per row of weights)")
    flat = np.take_along_axis(table, idx.reshape(lead + (-1,)), axis=-1)
    return flat.reshape(x.shape)


# ------------------------------------------------------------------------------------ Poisson-binomial


def _probabilities(q: ArrayLike) -> np.ndarray:
    a = np.asarray(q, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] == 0:
        raise ValueError(f"expected per-bit probabilities of shape [..., k] with k >= 1, got shape {a.shape}")
    if not np.all(np.isfinite(a)) or a.min() < 0.0 or a.max() > 1.0:
        raise ValueError("per-bit probabilities must be finite and in [0, 1]")
    return a


def poisson_binomial_pmf(q: ArrayLike) -> np.ndarray:
    """Distribution of the number of successes of independent Bernoulli(q_i) trials.

    Args:
        q: [..., k] success probabilities in [0, 1].

    Returns:
        [..., k + 1] float64: entry ``j`` is P(X = j). Exact dynamic programme (``O(k^2)`` per row, every
        term a sum of non-negative products, so small probabilities keep their relative accuracy).
    """
    a = _probabilities(q)
    k = a.shape[-1]
    pmf = np.zeros(a.shape[:-1] + (k + 1,))
    pmf[..., 0] = 1.0
    for i in range(k):
        qi = a[..., i : i + 1]
        pmf[..., 1 : i + 2] = pmf[..., 1 : i + 2] * (1.0 - qi) + pmf[..., : i + 1] * qi
        pmf[..., 0] *= 1.0 - a[..., i]
    return pmf


def poisson_binomial_sf(q: ArrayLike, x: ArrayLike) -> np.ndarray:
    """P(X >= x) for X the number of successes of independent Bernoulli(q_i) trials.

    Args:
        q: [..., k] success probabilities (the chance each bit matches on an unmarked image).
        x: number of successes (matching bits), an integer or integers broadcastable to ``q.shape[:-1]``.

    Returns:
        float64 array of shape ``broadcast(q.shape[:-1], x.shape)`` (0-d for one test): 1 for ``x <= 0``,
        0 for ``x > k``. The tail is a sum of the pmf from ``x`` up (no ``1 - cdf``).
    """
    pmf = poisson_binomial_pmf(q)
    xs = _integers(x, "x (the number of matching bits)")
    k = pmf.shape[-1] - 1
    tail = np.cumsum(pmf[..., ::-1], axis=-1)[..., ::-1]  # tail[..., j] = P(X >= j)
    tail = np.concatenate([tail, np.zeros(tail.shape[:-1] + (1,))], axis=-1)
    shape = np.broadcast_shapes(pmf.shape[:-1], xs.shape)
    idx = np.broadcast_to(np.clip(xs, 0, k + 1), shape)
    out = np.take_along_axis(np.broadcast_to(tail, shape + (k + 2,)), idx[..., None], axis=-1)[..., 0]
    return np.minimum(out, 1.0)


# ------------------------------------------------------------------------- combining dependent tests


def bonferroni_p_value(p_values: ArrayLike, axis: int = -1, weights: ArrayLike | None = None) -> np.ndarray:
    """``min(1, min_i p_i / w_i)`` over ``m`` p-values (weighted Bonferroni): valid under any dependence
    between them when the weights are non-negative, sum to at most 1 and are fixed -- or chosen from data
    under which each p-value stays valid (``P(p_i <= t) <= t`` given the weights): then
    ``P(min_i p_i / w_i <= a) <= sum_i w_i a <= a``.  Equal weights ``1 / m`` (the default) give
    ``min(1, m * min_i p_i)``.

    Used for the best of ``m`` readings of one image (:mod:`gsw.mark.evidence`): the selection of the
    smallest p-value is paid for by the weights.

    Args:
        p_values: [..., m, ...] p-values; ``axis`` is the one combined.
        axis: the axis combined.
        weights: [..., m, ...] broadcastable to ``p_values`` (the combined axis at the same place), summing
            to at most 1 along ``axis``; None: ``1 / m`` each.

    Returns:
        the combined p-values, ``axis`` removed.
    """
    p = np.asarray(p_values, dtype=np.float64)
    if p.ndim == 0 or p.shape[axis] == 0:
        raise ValueError("no p-values to combine")
    if weights is None:
        return np.minimum(1.0, p.shape[axis] * p.min(axis=axis))
    w = np.broadcast_to(np.asarray(weights, dtype=np.float64), p.shape)
    if w.min() < 0.0 or np.any(w.sum(axis=axis) > 1.0 + 1e-9):
        raise ValueError("Bonferroni weights must be >= 0 and sum to at most 1")
    with np.errstate(divide="ignore", invalid="ignore"):
        scaled = np.where(w > 0.0, p / np.where(w > 0.0, w, 1.0), np.inf)
    return np.minimum(1.0, scaled.min(axis=axis))


def hommel_combined_p_value(p_values: ArrayLike, axis: int = -1) -> np.ndarray:
    """Simes' combination with Hommel's correction: valid under arbitrary dependence between the tests.

    ``p = min(1, min_i n * H_n * p_(i) / i)`` with ``p_(1) <= ... <= p_(n)`` the sorted p-values and
    ``H_n = 1 + 1/2 + ... + 1/n`` (Hommel 1983, Biometrical Journal 25: the global test
    "reject if p_(i) <= i * alpha / (n * H_n) for some i" has level alpha for any joint distribution of
    the p-values). Why this rule for the frames of one scene: near-duplicate frames of an unmarked model
    decode to the same bits, so any method that needs independence (Fisher, Stouffer) counts one
    coincidence n times; this one never falls below the single-image p-value for n identical frames
    by more than the factor ``H_n`` (2.9 for 10 frames, 4.3 for 40), and rewards evidence spread over
    many frames (all n frames at p gives ``H_n * p``) far more than Bonferroni (``n * p``). One strong
    frame among n pays ``n * H_n``.

    Args:
        p_values: [..., n, ...] p-values in [0, 1]; ``axis`` is the one combined.

    Returns:
        combined p-values, ``axis`` removed (a 0-d array for a 1-D input).
    """
    p = np.asarray(p_values, dtype=np.float64)
    if p.ndim == 0 or p.shape[axis] == 0:
        raise ValueError("no p-values to combine")
    if not np.all(np.isfinite(p)) or p.min() < 0.0 or p.max() > 1.0:
        raise ValueError("p-values must be finite and in [0, 1]")
    p = np.moveaxis(p, axis, -1)
    n = p.shape[-1]
    harmonic = float(np.sum(1.0 / np.arange(1, n + 1)))
    scaled = np.sort(p, axis=-1) * (n * harmonic / np.arange(1, n + 1))
    return np.minimum(1.0, scaled.min(axis=-1))


# ------------------------------------------------------------------------------ binomial proportions


def _betacf(a: float, b: float, x: float) -> float:
    """Continued fraction of the regularised incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 10000):
        for num in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
                    -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + num * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + num / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def regularized_beta(a: float, b: float, x: float) -> float:
    """I_x(a, b), the CDF at ``x`` of Beta(a, b) (a, b > 0); P(Bin(n, p) >= j) = I_p(j, n - j + 1)."""
    if not (a > 0 and b > 0):
        raise ValueError(f"Beta parameters must be positive, got a={a}, b={b}")
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    log_front = (math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x)
                 + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return math.exp(log_front) * _betacf(a, b, x) / a
    return 1.0 - math.exp(log_front) * _betacf(b, a, 1.0 - x) / b


def beta_quantile(level: float, a: float, b: float) -> float:
    """The ``level`` quantile of Beta(a, b) (bisection on :func:`regularized_beta`, 1e-12 accuracy)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    lo, hi = 0.0, 1.0
    while hi - lo > 1e-12:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if regularized_beta(a, b, mid) < level else (lo, mid)
    return 0.5 * (lo + hi)


def clopper_pearson(successes: float, trials: float, level: float = 0.95) -> tuple[float, float]:
    """Exact (Clopper-Pearson) two-sided confidence interval of a binomial proportion.

    Args:
        successes: observed count (a non-integer count, e.g. an effective sample size, is accepted).
        trials: number of trials (> 0).
        level: coverage.

    Returns:
        (lower, upper); lower = 0 when there are no successes, upper = 1 when all trials succeeded.
    """
    if not trials > 0 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials and trials > 0, got {successes} of {trials}")
    tail = (1.0 - level) / 2.0
    lo = 0.0 if successes == 0 else beta_quantile(tail, successes, trials - successes + 1)
    hi = 1.0 if successes == trials else beta_quantile(1.0 - tail, successes + 1, trials - successes)
    return lo, hi
