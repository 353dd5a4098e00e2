"""Detection statistics: p-values of matching bits, their combination, the detection threshold.

Torch-free (``math`` and ``numpy`` only), shared by the embedder, the detector, the evaluation and the
decoder pre-training.

Example:
    >>> false_positive_threshold(32), false_positive_threshold(48), false_positive_threshold(64)
    (30, 41, 51)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

#: The false-positive rate at which a copy counts as watermarked (``gsw verify``, ``Verdict.detected``).
DETECTION_FPR = 1e-6


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
    """Fisher's method: combined p-value of independent tests (closed form for 2k degrees of freedom)."""
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
