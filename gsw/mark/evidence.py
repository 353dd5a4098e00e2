"""Evidence that images carry a message: :func:`assess`, the scoring rule of ``gsw verify`` and ``gsw identify``.

Two tests, by where the message came from (``origin``):

* ``"random"`` (default: gsw's own messages from ``os.urandom`` and ``key:<secret>`` messages): the exact
  randomization test of :mod:`gsw.mark.randomization`.  The probability is taken over the random draw of
  the message, with the images and the decoder's outputs fixed, so the p-value is exact for any image,
  any decoder bias and any dependence between frames.  Per image: its most confident reading (chosen
  without the message, so no multiple-testing factor), the signed-rank statistic of its logits.  Over
  images: the readings' logits pooled per bit and tested once.
* ``"chosen"`` (a message someone picked, e.g. ``gsw embed --message HEX``: it may line up with the
  decoder's biases on unmarked content): the calibrated null model.  For each image: read it at its scales
  (:func:`gsw.mark.scales.read_images`), the p-value of each reading's matching bits under the decoder's
  null model (:meth:`gsw.decoder.null.NullModel.p_values`: Poisson-binomial with the measured per-bit
  rates, an upper confidence bound for their estimation error, never below the fair coin), the smallest
  p-value over the readings in a weighted Bonferroni (:func:`reading_weights`: half of the level on the
  most confident reading, the other half split over all readings; 1 reading and no factor when the
  embedding size is known).  Over images: Simes' combination with Hommel's correction
  (:func:`gsw.stats.hommel_combined_p_value`), valid for any dependence between the images.  Its
  validity is an empirical claim about the null model, checked on hold-out data
  (``benchmarks/detection_null.py``, BENCHMARKS.md); it is conservative, so random messages use the exact
  test instead.

Example:
    >>> import torch
    >>> ev = assess([torch.rand(3, 128, 128)], torch.randint(0, 2, (32,)), num_bits=32)  # doctest: +SKIP
    >>> ev.detected(), ev.images[0].factor  # doctest: +SKIP
    (False, 1.0)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from gsw.decoder.null import NullModel, NullModelError, decoder_fingerprint, load_null_model, reading_direction
from gsw.mark.randomization import DEFAULT_WEIGHTING, check_weighting, choose_reading, exact_p_values, pooled_logits
from gsw.mark.scales import SEARCH_FACTORS, Reading, read_images
from gsw.stats import DETECTION_FPR, ORIGINS, bonferroni_p_value, check_origin, hommel_combined_p_value

__all__ = ["CONFIDENT_SHARE", "ORIGINS", "Evidence", "ImageEvidence", "Scores", "assess", "check_origin",
           "message_bits", "reading_weights", "resolve_null_model", "score_messages", "shipped_null_model"]

#: Share of an image's level given to its most confident reading in the scale search (:func:`reading_weights`).
CONFIDENT_SHARE = 0.5


@dataclass
class ImageEvidence:
    """One image's evidence.

    Attributes:
        bit_accuracy: fraction of the message's bits read at the chosen scale.
        matches: number of matching bits there.
        factor: resize factor of the chosen reading (1.0: the image as given).
        read_size: (height, width) the image was read at.
        readings: number of readings tried (random message: the most confident one is tested; chosen
            message: weighted Bonferroni over them, :func:`reading_weights`).
        p_value: the image's p-value, the scale search included.
    """

    bit_accuracy: float
    matches: int
    factor: float
    read_size: tuple[int, int]
    readings: int
    p_value: float


@dataclass
class Evidence:
    """Result of :func:`assess`.

    Attributes:
        images: per image, in input order.
        p_value: one p-value for all images together (valid for correlated frames).
        num_bits: message length.
        null_model: "exact" (random message: the randomization test), "calibrated" (chosen message: the
            decoder's null model) or "fair" (chosen message, fair coin: a custom decoder without a null model).
        origin: the message's origin (:data:`ORIGINS`).
    """

    images: list[ImageEvidence]
    p_value: float
    num_bits: int
    null_model: str
    origin: str = "random"

    @property
    def p_values(self) -> list[float]:
        """Per-image p-values."""
        return [e.p_value for e in self.images]

    @property
    def bit_accuracy(self) -> list[float]:
        """Per-image bit accuracy at the chosen scale."""
        return [e.bit_accuracy for e in self.images]

    @property
    def matches(self) -> list[int]:
        """Per-image matching bits at the chosen scale."""
        return [e.matches for e in self.images]

    def detected(self, fpr: float = DETECTION_FPR) -> bool:
        """Whether the combined p-value is at or below ``fpr``."""
        return self.p_value <= fpr


def message_bits(message: Tensor | Sequence[int] | np.ndarray, num_bits: int) -> np.ndarray:
    """The claimed message as [k] int8 bits; a clear error for a wrong length or non-bit values."""
    m = message.detach().cpu().numpy() if isinstance(message, Tensor) else np.asarray(message)
    if m.ndim != 1 or m.shape[0] != num_bits:
        raise ValueError(f"message has shape {list(m.shape)}; expected [{num_bits}] bits (num_bits={num_bits})")
    if not np.all((m == 0) | (m == 1)):
        raise ValueError("message must hold bits (0 or 1)")
    return m.astype(np.int8)


def reading_weights(confidence: Tensor | np.ndarray) -> np.ndarray:
    """Weighted-Bonferroni weights of one image's readings (see the module docstring).

    Args:
        confidence: [S] the readings' message-free confidence (:attr:`gsw.mark.scales.Reading.confidence`).

    Returns:
        [S] float64 weights summing to 1: ``(1 - CONFIDENT_SHARE) / S`` each, plus :data:`CONFIDENT_SHARE`
        on the most confident reading (the first among ties); ``[1.0]`` for one reading.
    """
    if isinstance(confidence, Tensor):
        confidence = confidence.detach().cpu().double().numpy()
    c = np.asarray(confidence, dtype=np.float64)
    if c.ndim != 1 or c.shape[0] == 0:
        raise ValueError(f"confidence must have shape [S] with S >= 1, got {list(c.shape)}")
    w = np.full(c.shape[0], (1.0 - CONFIDENT_SHARE) / c.shape[0])
    w[int(np.argmax(c))] += CONFIDENT_SHARE
    return w


@dataclass
class Scores:
    """Images scored against M messages at once (:func:`score_messages`).

    Attributes:
        p_values: [F, M] per image and message (random: the exact test of the chosen reading; chosen: the
            weighted Bonferroni over the image's readings, ``min_s p_s / w_s``, :func:`reading_weights`).
        matches: [F, M] matching bits at the chosen reading.
        chosen: [F, M] index of the chosen reading (random: the most confident one; chosen: the smallest
            ``p_s / w_s``, the first among ties).
        combined: [M] one p-value for the F images together, valid under any dependence between them
            (random: the exact test of the pooled logits; chosen: Hommel's combination).
    """

    p_values: np.ndarray
    matches: np.ndarray
    chosen: np.ndarray
    combined: np.ndarray


def score_messages(readings: Sequence[Reading], messages: np.ndarray, model: NullModel | None = None, *,
                   origin: str = "random", weighting: str = DEFAULT_WEIGHTING) -> Scores:
    """The p-values of decoded readings against M messages: the one scoring rule of :func:`assess` and
    :func:`gsw.mark.identify.identify`.

    Args:
        readings: per image, its readings (:func:`gsw.mark.scales.read_images`).
        messages: [M, k] message bits (int8 0/1).
        model: the decoder's null model (``origin="chosen"`` only: :meth:`NullModel.tail_table` per message
            and reading direction).
        origin: ``"random"`` (the exact randomization test, :mod:`gsw.mark.randomization`) or ``"chosen"``.
        weighting: per-bit weights of the exact test (:data:`gsw.mark.randomization.WEIGHTINGS`).

    Returns:
        :class:`Scores`.

    Raises:
        ValueError: a bad origin or weighting, ``origin="chosen"`` without a model, a reading of another
            bit length than the messages.
    """
    msgs = np.asarray(messages, dtype=np.int8)
    if msgs.ndim != 2:
        raise ValueError(f"messages must have shape [M, k], got {list(msgs.shape)}")
    k = msgs.shape[1]
    for r in readings:
        if r.logits.shape[-1] != k:
            raise ValueError(f"the decoder returned {r.logits.shape[-1]} bits, num_bits={k}")
    if check_origin(origin) == "random":
        check_weighting(weighting)
        return _score_random(readings, msgs, weighting)
    if model is None:
        raise ValueError("a chosen message is scored with the decoder's null model: pass model")
    return _score_chosen(readings, msgs, model)


def _score_random(readings: Sequence[Reading], msgs: np.ndarray, weighting: str) -> Scores:
    """The exact test: each image's most confident reading, the pooled logits for all images together."""
    chosen = np.array([choose_reading(r.confidence) for r in readings])
    logits = torch.stack([r.logits[c] for r, c in zip(readings, chosen)])  # [F, k]
    p, matches = exact_p_values(logits, msgs, weighting)
    combined = p[0] if len(readings) == 1 else exact_p_values(pooled_logits(logits), msgs, weighting)[0][0]
    return Scores(p, matches, np.repeat(chosen[:, None], msgs.shape[0], axis=1), combined)


def _score_chosen(readings: Sequence[Reading], msgs: np.ndarray, model: NullModel) -> Scores:
    """The calibrated null model: weighted Bonferroni over each image's readings, Hommel over images."""
    cols = np.arange(msgs.shape[0])
    tables: dict[str, np.ndarray] = {}

    def table(direction: str) -> np.ndarray:  # [M, k + 2], built only for the directions read
        if direction not in tables:
            tables[direction] = np.stack([model.tail_table(m, direction) for m in msgs])
        return tables[direction]

    p_rows, match_rows, chosen_rows = [], [], []
    for r in readings:
        bits = r.bits.numpy().astype(np.int32)  # [S, k]
        matches = bits @ msgs.T.astype(np.int32) + (1 - bits) @ (1 - msgs.T.astype(np.int32))  # [S, M]
        p = np.stack([table(reading_direction(f))[cols, row] for f, row in zip(r.factors, matches)])  # [S, M]
        w = reading_weights(r.confidence)[:, None]  # [S, 1]
        best = (p / w).argmin(axis=0)  # first among ties
        p_rows.append(bonferroni_p_value(p, axis=0, weights=w))
        match_rows.append(matches[best, cols])
        chosen_rows.append(best)
    p_values = np.stack(p_rows)
    return Scores(p_values, np.stack(match_rows), np.stack(chosen_rows), hommel_combined_p_value(p_values, axis=0))


_SHIPPED_NULLS: dict[tuple[int, str], NullModel] = {}


def shipped_null_model(num_bits: int, readout: str = "direct") -> NullModel:
    """The shipped null model of the ``num_bits`` decoder read directly or through ``readout`` (``"klein"``:
    :class:`gsw.decoder.KleinReadout`; :func:`gsw.decoder.null.load_null_model`), loaded once per process so
    that its tail tables (one per message) are computed once."""
    if (num_bits, readout) not in _SHIPPED_NULLS:
        _SHIPPED_NULLS[num_bits, readout] = load_null_model(num_bits, readout=readout)
    return _SHIPPED_NULLS[num_bits, readout]


def resolve_null_model(num_bits: int, decoder: torch.nn.Module, null: NullModel | None,
                       shipped_decoder: bool) -> tuple[NullModel, str]:
    """The null model to use with ``decoder`` and its label.

    An explicit ``null`` must belong to ``decoder`` (:meth:`NullModel.check_decoder`, else
    :class:`NullModelError`). Without one: the shipped decoder gets its shipped null model (sha256
    checked against the weights manifest); a custom decoder gets a shipped model whose decoder fingerprint
    is its own (the shipped weights, or :class:`gsw.decoder.KleinReadout` over them where a model calibrated
    through it ships), otherwise the fair coin."""
    if null is not None:
        if null.num_bits != num_bits:
            raise NullModelError(f"null model of {null.num_bits} bits given for num_bits={num_bits}")
        null.check_decoder(decoder)
        return null, "calibrated"
    try:
        shipped = shipped_null_model(num_bits)
    except NullModelError:
        if shipped_decoder:
            raise
        return NullModel.fair(num_bits), "fair"
    if shipped_decoder:
        shipped.check_decoder(decoder)
        return shipped, "calibrated"
    fingerprint = decoder_fingerprint(decoder)
    if shipped.decoder_fingerprint == fingerprint:
        return shipped, "calibrated"
    try:
        klein = shipped_null_model(num_bits, "klein")
    except NullModelError:
        return NullModel.fair(num_bits), "fair"
    return (klein, "calibrated") if klein.decoder_fingerprint == fingerprint else (NullModel.fair(num_bits), "fair")


@torch.no_grad()
def assess(images: Tensor | Sequence[Tensor], message: Tensor | Sequence[int] | np.ndarray, *, num_bits: int,
           decoder: torch.nn.Module | None = None, null: NullModel | None = None,
           embed_size: tuple[int, int] | None = None, factors: Sequence[float] = SEARCH_FACTORS,
           batch_size: int = 16, origin: str = "random", weighting: str = DEFAULT_WEIGHTING) -> Evidence:
    """Tests images for a message with p-values that hold for biased decoders, any number of correlated
    frames and an unknown display scale.

    With ``origin="random"`` the p-value is exact over the random draw of the message (the images fixed);
    a message someone chose must be tested with ``origin="chosen"`` (see the module docstring).

    Args:
        images: [3, H, W] RGB images in [0, 1] (a list, sizes may differ, or a [B, 3, H, W] batch).
        message: [k] claimed message bits.
        num_bits: k.
        decoder: default: the shipped ``num_bits`` decoder.
        null: the decoder's null model (chosen messages; default: :func:`resolve_null_model`); checked
            against the decoder when given with a random message, not used for it.
        embed_size: ``(height, width)`` of the embedding renders, when known: every image is read at
            that size only (no search, no multiple-testing factor).
        factors: scale-search factors (:data:`gsw.mark.scales.SEARCH_FACTORS`).
        batch_size: images of one shape decoded together.
        origin: ``"random"`` (default: gsw's own and ``key:`` messages) or ``"chosen"`` (:data:`ORIGINS`).
        weighting: per-bit weights of the exact test (random messages; :mod:`gsw.mark.randomization`).

    Returns:
        :class:`Evidence`.

    Raises:
        ValueError: wrong message length / values, bad images, a bad origin or weighting.
        gsw.decoder.null.NullModelError: a null model of another decoder or bit length.
    """
    m = message_bits(message, num_bits)
    check_origin(origin)
    check_weighting(weighting)
    shipped = decoder is None
    if shipped:
        from gsw.decoder.zoo import load_decoder

        first = images if isinstance(images, Tensor) else next(iter(images), None)
        # decode where the images are (a GPU render stays on the GPU)
        decoder = load_decoder(num_bits, device=first.device if isinstance(first, Tensor) else "cpu")
    out_bits = getattr(decoder, "num_bits", num_bits)
    if out_bits != num_bits:
        raise ValueError(f"the decoder reads {out_bits} bits, num_bits={num_bits}")
    if origin == "chosen" or null is not None:
        model, label = resolve_null_model(num_bits, decoder, null, shipped)
    if origin == "random":
        model, label = None, "exact"
    readings = read_images(images, decoder, embed_size=embed_size, factors=factors, batch_size=batch_size)
    sc = score_messages(readings, m[None], model, origin=origin, weighting=weighting)
    per_image = []
    for r, p, matches, best in zip(readings, sc.p_values[:, 0], sc.matches[:, 0], sc.chosen[:, 0]):
        per_image.append(ImageEvidence(int(matches) / num_bits, int(matches), r.factors[best], tuple(r.sizes[best]),
                                       len(r.factors), float(p)))
    return Evidence(per_image, float(sc.combined[0]), num_bits, label, origin)
