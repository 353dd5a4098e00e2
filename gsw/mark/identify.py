"""Identification: which registered recipient's mark do these images (or video frames) carry?

:func:`identify` decodes every image once per decoder found in the registry, then tests every registered
mark of that decoder against the decoded bits: one p-value per mark (:func:`_mark_p_value`, all images
taken together), then Holm's step-down correction over the marks tested, so the chance that an unmarked
source names *anyone* stays at or below ``fpr`` however many marks are registered (family-wise error
control under any dependence between the marks' tests). A recipient is identified when their adjusted
p-value is at or below ``fpr``.

The price of the correction: with M marks the best one must reach about ``fpr / M``. With one image at
the default 1e-6 and 1,000 marks, a 32-bit mark needs all 32 bits right; 48 and 64 bits leave room for
errors (:func:`gsw.stats.false_positive_threshold` at ``fpr / M``).

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

import torch
from torch import Tensor

from gsw.registry import Mark, Registry, shipped_decoder_sha256
from gsw.stats import DETECTION_FPR, binomial_p_value

__all__ = ["MarkResult", "Identification", "identify"]

ImageLike = Union[Tensor, Sequence[Tensor]]


def _mark_p_value(bits_per_frame: Tensor, message: Tensor) -> float:
    """P-value of "these frames carry ``message``": the chance an unmarked source matches as well.

    Today a conservative value that holds however correlated the frames are (a video's frames are
    near-duplicates, so Fisher's independence assumption would be optimistic): Bonferroni over the F
    frames of the per-frame binomial p-value, ``min(1, F * min_f P(Bin(k, 1/2) >= matches_f))``. It assumes
    each frame of an unmarked source reads k fair coin flips. This function is the hook that the
    calibrated per-decoder null model replaces; :func:`identify` calls nothing else to score a mark.

    Args:
        bits_per_frame: [F, k] decoded bits in {0, 1}, one row per image/frame.
        message: [k] the mark's bits in {0, 1}.

    Returns:
        The p-value in (0, 1].
    """
    frames, k = bits_per_frame.shape
    best = int((bits_per_frame == message.to(bits_per_frame)).sum(dim=1).max())
    return min(1.0, frames * binomial_p_value(best, k))


def _holm(p_values: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values (family-wise error control under any dependence)."""
    m = len(p_values)
    adjusted = [1.0] * m
    running = 0.0
    for rank, i in enumerate(sorted(range(m), key=lambda j: p_values[j])):
        running = max(running, min(1.0, (m - rank) * p_values[i]))
        adjusted[i] = running
    return adjusted


@dataclass
class MarkResult:
    """One registered mark tested against the images.

    Attributes:
        mark: the registry entry (its message stays out of ``repr`` and of :meth:`to_dict` by default).
        p_value: :func:`_mark_p_value` of all images together.
        adjusted_p_value: Holm-adjusted over every mark tested.
        matches: per image, the number of message bits read correctly.
        identified: ``adjusted_p_value <= fpr``.
    """

    mark: Mark
    p_value: float
    adjusted_p_value: float
    matches: list[int]
    identified: bool

    @property
    def best_bit_accuracy(self) -> float:
        """Share of the message bits read correctly in the best image."""
        return max(self.matches) / self.mark.num_bits

    def to_dict(self, show_secret: bool = False) -> dict[str, Any]:
        """JSON-ready: id, label, bits, p-values, per-image matches (the message only with ``show_secret``)."""
        out = {"id": self.mark.id, "label": self.mark.label, "num_bits": self.mark.num_bits,
               "p_value": self.p_value, "adjusted_p_value": self.adjusted_p_value, "identified": self.identified,
               "best_bit_accuracy": self.best_bit_accuracy, "matches": self.matches}
        if show_secret:
            out["message_hex"] = self.mark.message_hex
        return out


@dataclass
class Identification:
    """Result of :func:`identify`.

    Attributes:
        identified: the marks whose adjusted p-value is at or below ``fpr``, most significant first.
        results: every mark tested, most significant first.
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
                "num_images": self.num_images, "marks_tested": len(self.results),
                "skipped": [{"id": m.id, "label": m.label, "decoder_sha256": m.decoder_sha256} for m in self.skipped],
                "results": [r.to_dict(show_secret) for r in self.results]}


def _groups(marks: Sequence[Mark], decoders: Mapping[str, torch.nn.Module]
            ) -> tuple[dict[tuple[str, int], list[Mark]], list[Mark]]:
    """Marks by (decoder sha256, bits) with a usable decoder, and the marks without one."""
    shipped: dict[int, str | None] = {}
    groups: dict[tuple[str, int], list[Mark]] = {}
    skipped = []
    for mark in marks:
        k = mark.num_bits
        if k not in shipped:
            try:
                shipped[k] = shipped_decoder_sha256(k)
            except RuntimeError:  # WeightsError: no shipped decoder of that length
                shipped[k] = None
        if mark.decoder_sha256 in decoders or mark.decoder_sha256 == shipped[k]:
            groups.setdefault((mark.decoder_sha256, k), []).append(mark)
        else:
            skipped.append(mark)
    return groups, skipped


def identify(images: ImageLike, registry: Registry | Sequence[Mark], *, fpr: float = DETECTION_FPR,
             decoders: Mapping[str, torch.nn.Module] | None = None,
             device: str | torch.device | None = None) -> Identification:
    """Tests images against every registered mark and names the recipients they identify.

    Args:
        images: [3,H,W], [B,3,H,W] or a list of [3,H,W] RGB images in [0, 1] (e.g. the frames of one
            video, :func:`gsw.io.video.load_images_or_video`); all are taken as one source.
        registry: an open :class:`~gsw.registry.Registry`, or the marks to test.
        fpr: family-wise false-positive rate: the chance that an unmarked source identifies anyone.
        decoders: custom decoders (LL2 subband -> logits) by the sha256 their marks record; the shipped
            decoders are used for marks that record a shipped decoder's sha256.
        device: where to decode (default: where the images are).

    Returns:
        An :class:`Identification`.

    Raises:
        ValueError: no images, a malformed image, or ``fpr`` outside (0, 1).
    """
    if not 0.0 < fpr < 1.0:
        raise ValueError(f"fpr must lie in (0, 1), got {fpr}")
    from gsw.mark import extract  # the detection path (it needs the package, not the rasterizer)

    if isinstance(images, Tensor):
        images = list(images.unsqueeze(0) if images.dim() == 3 else images)
    images = [img.to(device) if device is not None else img for img in images]
    if not images:
        raise ValueError("no images given")
    marks = registry.list() if isinstance(registry, Registry) else list(registry)
    groups, skipped = _groups(marks, decoders or {})
    tested: list[tuple[Mark, float, list[int]]] = []
    for (sha, k), group in groups.items():
        bits = extract(images, num_bits=k, decoder=(decoders or {}).get(sha)).bits.cpu()  # [F, k], once
        messages = torch.stack([m.message for m in group])  # [M, k]
        matches = (bits[None] == messages[:, None]).sum(dim=2)  # [M, F]
        for mark, message, row in zip(group, messages, matches.tolist()):
            tested.append((mark, _mark_p_value(bits, message), row))
    adjusted = _holm([p for _, p, _ in tested])
    results = sorted((MarkResult(m, p, a, row, a <= fpr) for (m, p, row), a in zip(tested, adjusted)),
                     key=lambda r: (r.adjusted_p_value, r.p_value, r.mark.id))
    return Identification([r for r in results if r.identified], results, skipped, len(images), fpr)
