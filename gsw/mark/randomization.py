"""The exact randomization (key) test on the decoder's soft outputs: p-values for random messages.

What is random: the message.  gsw's default messages come from the OS entropy pool and ``key:<secret>``
messages from SHA-256 of the secret, so each of the ``k`` bits is a fair coin drawn independently of any
image the message is later tested on.  Over that draw -- and only over it -- the probability is taken:
the image, the decoder and whatever the decoder outputs on it are held fixed.  Then, whatever the decoder
reads (biased bits, correlated bits, the same bits on 40 near-identical frames), bit ``i`` of the message
agrees with the bit read with probability exactly 1/2, independently of the other bits.  A statistic
``sum_i w_i [bit i matches]`` whose weights ``w_i`` depend on the decoder's output only (never on the
message) is therefore distributed like ``sum_i w_i B_i`` with ``B_i`` iid Bernoulli(1/2), and its tail
(:func:`gsw.stats.weighted_sign_sf`, exact dynamic programme over integer weights) is an exact p-value:
no calibration data, no correlation factor, no assumption about the content.

The pieces, all message-free:

* **weights** (:func:`bit_weights`): ``"rank"`` (default): the rank of ``|logit_i|`` among the ``k`` bits
  (1 = least confident, ties by index): the Wilcoxon signed-rank statistic, so confidently read bits
  count more than doubtful ones; ``"sign"``: every bit 1 (the number of matching bits, the fair-coin
  binomial test); ``"magnitude"``: ``|logit_i|`` over the reading's median ``|logit|``, clipped at
  :data:`MAGNITUDE_CLIP` and quantised to :data:`MAGNITUDE_LEVELS` steps per median.
* **scale search** (:func:`choose_reading`): an image read at several scales keeps its most confident
  reading (largest mean ``|logit|``, :attr:`gsw.mark.scales.Reading.confidence`); the choice does not
  look at the message, so the chosen reading's p-value is exact without a multiple-testing factor.
* **several images** (:func:`pooled_logits`): the chosen readings' logits, each divided by its median
  ``|logit|``, summed per bit, and tested once: one random message, one test, exact for any dependence
  between the frames.

For a message someone *chose* (a hex string typed by a user, a message aligned with the decoder's biases)
none of this holds: use the calibrated null model (:mod:`gsw.decoder.null`,
``origin="chosen"`` in :func:`gsw.mark.evidence.assess`).

Example:
    >>> import torch
    >>> logits = torch.tensor([[2.0, -0.1, 0.5, -3.0]])
    >>> bit_weights(logits).tolist()
    [[3, 1, 2, 4]]
    >>> p, matches = exact_p_values(logits, np.array([[1, 0, 1, 0]]))
    >>> float(p[0, 0]) == 1 / 16, int(matches[0, 0])
    (True, 4)
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from gsw.stats import weighted_sign_sf

__all__ = ["DEFAULT_WEIGHTING", "MAGNITUDE_CLIP", "MAGNITUDE_LEVELS", "WEIGHTINGS", "bit_weights",
           "check_weighting", "choose_reading", "exact_p_values", "logit_scale", "pooled_logits"]

#: The per-bit weightings of the exact test (:func:`bit_weights`).
WEIGHTINGS = ("rank", "sign", "magnitude")
#: The weighting of ``gsw verify`` / ``gsw identify`` (chosen on a tuning set, BENCHMARKS.md).
DEFAULT_WEIGHTING = "rank"
#: ``"magnitude"`` weights: ``|logit|`` is clipped at this many medians ...
MAGNITUDE_CLIP = 3.0
#: ... and quantised to this many integer steps per median.
MAGNITUDE_LEVELS = 8


def _as_array(logits: Tensor | np.ndarray) -> np.ndarray:
    a = logits.detach().cpu().double().numpy() if isinstance(logits, Tensor) else np.asarray(logits, np.float64)
    if a.ndim == 0 or a.shape[-1] == 0:
        raise ValueError(f"expected logits of shape [..., k] with k >= 1, got {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise ValueError("logits must be finite")
    return a


def check_weighting(weighting: str) -> str:
    """``weighting`` if it is one of :data:`WEIGHTINGS`, else a ValueError naming them."""
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {', '.join(WEIGHTINGS)}, got {weighting!r}")
    return weighting


def logit_scale(logits: Tensor | np.ndarray) -> np.ndarray:
    """[...] median ``|logit|`` over the bits of each reading ([..., k]); 1 where it is 0 (message-free)."""
    med = np.median(np.abs(_as_array(logits)), axis=-1)
    return np.where(med > 0, med, 1.0)


def bit_weights(logits: Tensor | np.ndarray, weighting: str = DEFAULT_WEIGHTING) -> np.ndarray:
    """Integer weight of each bit of each reading, from the logits alone (never the message).

    Args:
        logits: [..., k] decoder logits (bit = logit > 0).
        weighting: one of :data:`WEIGHTINGS` (see the module docstring).

    Returns:
        [..., k] int64 weights >= 0.
    """
    a = np.abs(_as_array(logits))
    check_weighting(weighting)
    if weighting == "sign":
        return np.ones(a.shape, dtype=np.int64)
    if weighting == "rank":
        return np.argsort(np.argsort(a, axis=-1, kind="stable"), axis=-1, kind="stable").astype(np.int64) + 1
    rel = np.minimum(a / logit_scale(a)[..., None], MAGNITUDE_CLIP)
    return np.round(MAGNITUDE_LEVELS * rel).astype(np.int64)


def choose_reading(confidence: Tensor | np.ndarray) -> int:
    """Index of the most confident of an image's readings (the first among ties): the scale search's pick.

    Args:
        confidence: [S] message-free confidence of each reading (:attr:`gsw.mark.scales.Reading.confidence`).
    """
    c = confidence.detach().cpu().double().numpy() if isinstance(confidence, Tensor) else np.asarray(confidence)
    if c.ndim != 1 or c.shape[0] == 0:
        raise ValueError(f"confidence must have shape [S] with S >= 1, got {list(c.shape)}")
    return int(np.argmax(c))


def pooled_logits(logits: Sequence[Tensor] | Tensor | np.ndarray) -> np.ndarray:
    """[k] the frames' logits pooled per bit: ``sum_f logits_f / median |logits_f|`` (message-free).

    Args:
        logits: [F, k] one (chosen) reading per frame.
    """
    a = _as_array(torch.stack(list(logits)) if isinstance(logits, (list, tuple)) else logits)
    if a.ndim != 2:
        raise ValueError(f"expected [F, k] logits (one reading per frame), got {list(a.shape)}")
    return (a / logit_scale(a)[:, None]).sum(0)


def exact_p_values(logits: Tensor | np.ndarray, messages: np.ndarray,
                   weighting: str = DEFAULT_WEIGHTING) -> tuple[np.ndarray, np.ndarray]:
    """Exact p-values of readings against M random messages.

    Args:
        logits: [R, k] (or [k]) one reading per row.
        messages: [M, k] message bits (0/1).
        weighting: see :func:`bit_weights`.

    Returns:
        ``(p [R, M], matches [R, M])``: the p-value of the total weight of the matching bits
        (:func:`gsw.stats.weighted_sign_sf`) and the number of matching bits.
    """
    a = _as_array(logits)
    a = a[None] if a.ndim == 1 else a
    m = np.asarray(messages)
    if m.ndim != 2 or m.shape[1] != a.shape[-1]:
        raise ValueError(f"messages have shape {list(m.shape)}; expected [M, {a.shape[-1]}]")
    if not np.all((m == 0) | (m == 1)):
        raise ValueError("messages must hold bits (0 or 1)")
    w = bit_weights(a, weighting)
    bits = (a > 0).astype(np.int64)
    m64 = m.astype(np.int64)
    matched = (bits * w) @ m64.T + ((1 - bits) * w) @ (1 - m64).T  # [R, M] weight of the matching bits
    matches = bits @ m64.T + (1 - bits) @ (1 - m64).T
    return weighted_sign_sf(w, matched), matches
