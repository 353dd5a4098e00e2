"""Identification: which registered recipient's mark do these images (or video frames) carry?

:func:`identify` reads the images once per decoder and embedding size found in the registry (a mark that
records its embedding resolution is read at that size, the others with the scale search), then scores
every registered mark with the evidence of :func:`gsw.verify` (:func:`gsw.mark.evidence.score_messages`)
for the mark's message origin (:attr:`gsw.registry.Mark.origin`): a random message (gsw's default, a key)
with the exact randomization test, exact over the random draw of that mark's message whatever the images;
a chosen message with the decoder's calibrated null model (Hommel over the images).  Then Holm's step-down
correction over the marks tested, so the chance that an unmarked source names *anyone* stays at or below
``fpr`` however many marks are registered (family-wise error control under any dependence between the
marks' tests). A recipient is identified when their adjusted p-value is at or below ``fpr``.

Screening of chosen messages (speed, same decisions): a calibrated p-value is never below the fair-coin
one computed from the same readings, and Holm's decisions depend only on the p-values at or below ``fpr``
(and on the number of marks). So the calibrated value (one tail table per message) is computed for every
chosen mark whose fair-coin value is at or below ``fpr``, and for the ``exact`` best others; the remaining
marks keep their fair-coin value, a lower bound already above ``fpr`` (``MarkResult.exact`` is False).
Random messages need no screening: their exact p-values cost one matrix product for all marks.

:func:`identify` is three steps, public for callers that test many sources (``gsw scan``,
:mod:`gsw.fingerprint.scan`): :func:`plan_identify` (marks grouped by decoder and embedding size, each
decoder loaded once), :func:`decode_sources` (the decoding: the images of many sources through each decoder
in batches) and :func:`identify_readings` (the testing of one source from its decoder outputs). Decoder
outputs depend on the batch only by float rounding (summation order of the kernels); the tests read signs
and ranks of the logits, so a source's p-values and decisions do not depend on the sources decoded with it
unless two of its logits lie within that rounding of each other (or of 0).

The price of the correction: with M marks the best one must reach about ``fpr / M``. With one image at
the default 1e-6 and 1,000 marks, a 32-bit mark needs all 32 bits right; 48 and 64 bits leave room for
errors.

Example:
    >>> from gsw.registry import open_registry       # doctest: +SKIP
    >>> with open_registry() as reg:                  # doctest: +SKIP
    ...     found = identify(frames, reg)
    >>> [r.mark.label for r in found.identified]      # doctest: +SKIP
    ['alice']
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Union

import numpy as np
import torch
from torch import Tensor

from gsw.decoder.null import NullModel
from gsw.mark.evidence import resolve_null_model, score_messages
from gsw.mark.scales import Reading, read_images
from gsw.registry import Mark, Registry, shipped_decoder_sha256
from gsw.stats import DETECTION_FPR, ORIGINS

__all__ = ["DecoderGroup", "Identification", "IdentifyPlan", "MarkBatch", "MarkResult", "SourceReadings",
           "decode_sources", "identify", "identify_readings", "plan_identify"]

ImageLike = Union[Tensor, Sequence[Tensor]]


def _holm(p_values: np.ndarray) -> np.ndarray:
    """Holm's step-down adjusted p-values (family-wise error control under any dependence).

    Args:
        p_values: [M] float64 p-values.

    Returns:
        [M] adjusted p-values: ``max over j <= rank(i) of min(1, (M - j) p_(j))``, ties ranked in input order.
    """
    p = np.asarray(p_values, dtype=np.float64)
    m = p.size
    order = np.argsort(p, kind="stable")
    adjusted = np.empty(m)
    adjusted[order] = np.maximum.accumulate(np.minimum(1.0, (m - np.arange(m)) * p[order])) if m else p
    return adjusted


@dataclass
class MarkResult:
    """One registered mark tested against the images.

    Attributes:
        mark: the registry entry (its message stays out of ``repr`` and of :meth:`to_dict` by default).
        p_value: the p-value of all images together (as :func:`gsw.verify` computes it for the mark's
            origin), or, when ``exact`` is False, its fair-coin lower bound (then above ``fpr``).
        adjusted_p_value: Holm-adjusted over every mark tested.
        matches: per image, the number of message bits read correctly at the chosen scale.
        identified: ``adjusted_p_value <= fpr``.
        exact: whether ``p_value`` is the value itself rather than a screening bound (module docstring).
    """

    mark: Mark
    p_value: float
    adjusted_p_value: float
    matches: list[int]
    identified: bool
    exact: bool = True

    @property
    def best_bit_accuracy(self) -> float:
        """Share of the message bits read correctly in the best image."""
        return max(self.matches) / self.mark.num_bits

    def to_dict(self, show_secret: bool = False) -> dict[str, Any]:
        """JSON-ready: id, label, bits, p-values, per-image matches (the message only with ``show_secret``)."""
        out = {"id": self.mark.id, "label": self.mark.label, "num_bits": self.mark.num_bits,
               "p_value": self.p_value, "adjusted_p_value": self.adjusted_p_value, "identified": self.identified,
               "p_value_exact": self.exact, "origin": self.mark.origin, "best_bit_accuracy": self.best_bit_accuracy, "matches": self.matches}
        if show_secret:
            out["message_hex"] = self.mark.message_hex
        return out


@dataclass
class Identification:
    """Result of :func:`identify`.

    Attributes:
        identified: the marks whose adjusted p-value is at or below ``fpr``, most significant first.
        results: every mark tested, most significant first (only the best ones when
            :func:`identify_readings` was given ``keep``).
        skipped: marks not tested because their decoder is neither shipped nor given.
        num_images: images (frames) read.
        fpr: the family-wise false-positive rate of the decision.
    """

    identified: list[MarkResult]
    results: list[MarkResult]
    skipped: list[Mark]
    num_images: int
    fpr: float

    @property
    def recipients(self) -> list[str]:
        """Labels of the identified marks."""
        return [r.mark.label for r in self.identified]

    def to_dict(self, show_secret: bool = False) -> dict[str, Any]:
        """JSON-ready summary (messages only with ``show_secret``)."""
        return {"identified": [r.to_dict(show_secret) for r in self.identified],
                "recipients": self.recipients, "fpr": self.fpr, "correction": "holm",
                "null_model": "random messages: exact randomization test; chosen messages: calibrated (per "
                              "decoder; fair coin for custom decoders without one)",
                "num_images": self.num_images, "marks_tested": len(self.results),
                "skipped": [{"id": m.id, "label": m.label, "decoder_sha256": m.decoder_sha256} for m in self.skipped],
                "results": [r.to_dict(show_secret) for r in self.results]}


@dataclass
class MarkBatch:
    """The marks of one decoder, embedding size and origin: tested together by one test.

    Attributes:
        size: embedding size ``(height, width)`` of the marks, None for marks without one (scale search).
        origin: ``"random"`` or ``"chosen"`` (:data:`gsw.stats.ORIGINS`).
        marks: the marks.
        messages: [M, k] their message bits (int8 0/1).
    """

    size: tuple[int, int] | None
    origin: str
    marks: list[Mark]
    messages: np.ndarray


@dataclass
class DecoderGroup:
    """The marks read by one decoder.

    Attributes:
        sha256: the decoder's sha256 (what its marks record).
        num_bits: message length k.
        decoder: the frozen decoder (images [B, 3, H, W] or LL2 subband -> logits [B, k]), on the device.
        null_model: its null model (chosen messages; the fair coin for a custom decoder without one).
        fair: the fair-coin model of k bits (screening of chosen messages).
        batches: its marks by embedding size and origin.
    """

    sha256: str
    num_bits: int
    decoder: torch.nn.Module
    null_model: NullModel
    fair: NullModel
    batches: list[MarkBatch]

    @property
    def sizes(self) -> list[tuple[int, int] | None]:
        """The embedding sizes its images are read at (None: the scale search), in order."""
        return list(dict.fromkeys(b.size for b in self.batches))


@dataclass
class IdentifyPlan:
    """What :func:`decode_sources` reads and :func:`identify_readings` tests: built once for many sources by
    :func:`plan_identify` (decoders loaded and checked, null models resolved).

    Attributes:
        groups: one per decoder of the tested marks.
        skipped: marks not tested because their decoder is neither shipped nor given.
    """

    groups: list[DecoderGroup]
    skipped: list[Mark]


@dataclass
class SourceReadings:
    """One source's decoder outputs (:func:`decode_sources`).

    Attributes:
        num_images: images (frames) of the source.
        readings: per ``(group index, embedding size)`` of the plan, one :class:`~gsw.mark.scales.Reading`
            per image, in order.
    """

    num_images: int
    readings: dict[tuple[int, tuple[int, int] | None], list[Reading]]


def plan_identify(registry: Registry | Sequence[Mark], *, decoders: Mapping[str, torch.nn.Module] | None = None,
                  device: str | torch.device = "cpu") -> IdentifyPlan:
    """Groups the marks by decoder and embedding size, loads each decoder once on ``device``.

    Args:
        registry: an open :class:`~gsw.registry.Registry`, or the marks to test.
        decoders: custom decoders by the sha256 their marks record (see :func:`identify`); marks embedded through
            :class:`gsw.decoder.KleinReadout` over a shipped decoder are recognised without it.
        device: where to decode.

    Returns:
        An :class:`IdentifyPlan`.

    Raises:
        ValueError: a custom decoder that does not output ``[1, num_bits]``.
    """
    from gsw.mark.detect import load_decoder_for

    from gsw.decoder.readout import KleinReadout, shipped_klein_fingerprint

    marks = registry.list() if isinstance(registry, Registry) else list(registry)
    decoders = dict(decoders or {})
    shipped: dict[int, str | None] = {}
    by_decoder: dict[tuple[str, int], list[Mark]] = {}
    skipped = []
    for mark in marks:
        k = mark.num_bits
        if k not in shipped:
            try:
                shipped[k] = shipped_decoder_sha256(k)
            except RuntimeError:  # WeightsError: no shipped decoder of that length
                shipped[k] = None
        if mark.decoder_sha256 not in decoders and shipped[k] is not None and mark.decoder_sha256 != shipped[k] \
                and mark.decoder_sha256 == shipped_klein_fingerprint(k):  # embedded through KleinReadout
            from gsw.decoder.zoo import load_decoder

            decoders[mark.decoder_sha256] = KleinReadout(load_decoder(k))
        if mark.decoder_sha256 in decoders or mark.decoder_sha256 == shipped[k]:
            by_decoder.setdefault((mark.decoder_sha256, k), []).append(mark)
        else:
            skipped.append(mark)
    groups = []
    for (sha, k), group in by_decoder.items():
        custom = decoders.get(sha)
        decoder = load_decoder_for(k, custom, torch.device(device))
        model, _ = resolve_null_model(k, decoder, None, custom is None)
        by_size: dict[tuple[int, int] | None, list[Mark]] = {}
        for mark in group:
            by_size.setdefault((mark.height, mark.width) if mark.width and mark.height else None, []).append(mark)
        batches = [MarkBatch(size, origin, same, np.stack([m.message.numpy() for m in same]).astype(np.int8))
                   for size, marks_of_size in by_size.items() for origin in ORIGINS
                   if (same := [m for m in marks_of_size if m.origin == origin])]
        groups.append(DecoderGroup(sha, k, decoder, model, NullModel.fair(k), batches))
    return IdentifyPlan(groups, skipped)


def decode_sources(sources: Sequence[Sequence[Tensor]], plan: IdentifyPlan, *,
                   batch_size: int = 16) -> list[SourceReadings]:
    """Runs every decoder of ``plan`` over the images of many sources together (the decoding half of
    :func:`identify`).

    For each decoder and embedding size, the images of all sources are read by
    :func:`gsw.mark.scales.read_images`: images of one shape go through the decoder in batches of up to
    ``batch_size``, whichever source they come from (each read at every scale of the search, or once at the
    embedding size).

    Args:
        sources: per source, its [3, H, W] RGB images in [0, 1] (sizes may differ), on any device.
        plan: :func:`plan_identify`.
        batch_size: at most this many images of one shape per decoder call.

    Returns:
        One :class:`SourceReadings` per source, in order.

    Raises:
        ValueError: a source without images, a malformed image, ``batch_size`` < 1.
    """
    flat: list[Tensor] = []
    counts = []
    for s, images in enumerate(sources):
        if len(images) == 0:
            raise ValueError(f"source {s}: no images given")
        flat += list(images)
        counts.append(len(images))
    out = [SourceReadings(n, {}) for n in counts]
    if not flat:
        return out
    for g, group in enumerate(plan.groups):
        for size in group.sizes:
            readings = read_images(flat, group.decoder, embed_size=size, batch_size=batch_size)  # once per size
            start = 0
            for src, n in zip(out, counts):
                src.readings[(g, size)] = readings[start:start + n]
                start += n
    return out


def identify_readings(source: SourceReadings, plan: IdentifyPlan, *, fpr: float = DETECTION_FPR,
                      exact: int = 10, keep: int | None = None) -> Identification:
    """Tests one source's readings against every mark of ``plan`` (the testing half of :func:`identify`):
    each mark by its origin's test, then Holm's correction over all marks tested.

    Args:
        source: the source's readings (:func:`decode_sources` with the same ``plan``).
        plan: :func:`plan_identify`.
        fpr: family-wise false-positive rate.
        exact: see :func:`identify`.
        keep: report only the ``keep`` most significant marks in ``results`` (and every identified one); None:
            all. Every mark is tested and counted by Holm's correction either way (a scan against thousands of
            marks needs only the best one).

    Returns:
        An :class:`Identification`.

    Raises:
        ValueError: ``fpr`` outside (0, 1).
    """
    if not 0.0 < fpr < 1.0:
        raise ValueError(f"fpr must lie in (0, 1), got {fpr}")
    if keep is not None and keep < 0:
        raise ValueError(f"keep must be >= 0 or None, got {keep}")
    marks: list[Mark] = []
    p_values, matches, exact_flags = [], [], []
    for g, group in enumerate(plan.groups):
        for batch in group.batches:
            score = _score_random if batch.origin == "random" else _score_chosen
            p, m, was_exact = score(source.readings[(g, batch.size)], batch, group, fpr, exact)
            marks += batch.marks
            p_values.append(p)
            matches.append(m)
            exact_flags.append(was_exact)
    if not marks:
        return Identification([], [], plan.skipped, source.num_images, fpr)
    p_all, exact_all = np.concatenate(p_values), np.concatenate(exact_flags)
    adjusted = _holm(p_all)
    order = np.lexsort((np.array([m.id for m in marks]), p_all, adjusted))  # by adjusted p, then p, then id
    if keep is not None:
        order = order[:max(keep, int(np.count_nonzero(adjusted <= fpr)))]  # the identified ones come first
    # whole arrays to Python at once (pulling values out one mark at a time cost ~10 us a mark)
    rows = np.concatenate(matches, axis=1)[:, order].T.tolist()
    ps, adj, ex = p_all[order].tolist(), adjusted[order].tolist(), exact_all[order].tolist()
    results = [MarkResult(marks[i], p, a, row, a <= fpr, e) for i, p, a, row, e in zip(order.tolist(), ps, adj, rows, ex)]
    return Identification([r for r in results if r.identified], results, plan.skipped, source.num_images, fpr)


def _score_random(readings: list[Reading], batch: MarkBatch, group: DecoderGroup, fpr: float,
                  exact: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random messages: the exact randomization test of every mark (``group``, ``fpr``, ``exact`` unused).

    Returns:
        p-values [M], matching bits [F, M] at the chosen readings, and [M] True (every p-value exact).
    """
    sc = score_messages(readings, batch.messages, origin="random")
    return sc.combined, sc.matches, np.ones(len(batch.marks), dtype=bool)


def _score_chosen(readings: list[Reading], batch: MarkBatch, group: DecoderGroup, fpr: float,
                  exact: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chosen messages: the calibrated null model, screened by the fair coin (see the module docstring).

    Returns:
        p-values [M], matching bits [F, M] at the chosen readings, and [M] whether the mark's p-value is the
        calibrated one (else the fair coin's lower bound).
    """
    messages = batch.messages
    fair = score_messages(readings, messages, group.fair, origin="chosen")
    order = np.argsort(fair.combined, kind="stable")
    todo = sorted(set(order[:exact].tolist()) | set(np.flatnonzero(fair.combined <= fpr).tolist()))
    p, matches = fair.combined.astype(np.float64), fair.matches.copy()
    calibrated = np.zeros(len(batch.marks), dtype=bool)
    if todo:
        sc = score_messages(readings, messages[todo], group.null_model, origin="chosen")
        p[todo], matches[:, todo], calibrated[todo] = sc.combined, sc.matches, True
    return p, matches, calibrated


def identify(images: ImageLike, registry: Registry | Sequence[Mark], *, fpr: float = DETECTION_FPR,
             decoders: Mapping[str, torch.nn.Module] | None = None,
             device: str | torch.device | None = None, exact: int = 10) -> Identification:
    """Tests images against every registered mark and names the recipients they identify.

    Args:
        images: [3,H,W], [B,3,H,W] or a list of [3,H,W] RGB images in [0, 1] (e.g. the frames of one
            video, :func:`gsw.io.video.load_images_or_video`); all are taken as one source.
        registry: an open :class:`~gsw.registry.Registry`, or the marks to test.
        fpr: family-wise false-positive rate: the chance that an unmarked source identifies anyone.
        decoders: custom decoders (LL2 subband -> logits) by the sha256 their marks record; the shipped
            decoders are used for marks that record a shipped decoder's sha256, and
            :class:`gsw.decoder.KleinReadout` over a shipped decoder for marks that record its fingerprint
            (:func:`gsw.decoder.readout.shipped_klein_fingerprint`). A custom decoder's p-values use the fair coin
            (for chosen messages) unless its weights are the shipped ones.
        device: where to decode (default: where the images are).
        exact: besides the marks that could be identified, the calibrated p-value is computed for this many
            best marks of each decoder and embedding size (for reporting; decisions do not depend on it).

    Returns:
        An :class:`Identification`.

    Raises:
        ValueError: no images, a malformed image, or ``fpr`` outside (0, 1).
    """
    if not 0.0 < fpr < 1.0:
        raise ValueError(f"fpr must lie in (0, 1), got {fpr}")
    from gsw.mark.detect import _as_images

    if isinstance(images, Tensor):
        images = list(images.unsqueeze(0) if images.dim() == 3 else images)
    images = [img.to(device) if device is not None else img for img in images]
    if not images:
        raise ValueError("no images given")
    images = [img[0] for img in _as_images(images)]
    plan = plan_identify(registry, decoders=decoders, device=images[0].device)
    return identify_readings(decode_sources([images], plan)[0], plan, fpr=fpr, exact=exact)
