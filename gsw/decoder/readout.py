"""Readouts of a decoder's logits: the flip-antisymmetric ``KleinReadout`` (issue #22).

A decoder ``D`` (LL2 subband -> k logits, bit = sign) leans one way per bit on unmarked images (BENCHMARKS.md, #22:
the shipped decoders' worst bit deviates from P(1) = 1/2 by 0.19-0.30 on held-out photos, p < 2e-4). Reading it
through ``K(ll) = (D(ll) - D(h ll) - D(v ll) + D(r ll)) / 2`` (h, v: the horizontal and vertical flips of the subband,
r = h v the half turn) cancels any such lean: each flip of the subband negates ``K``, so on a population of subbands
that is as likely flipped as not, every bit of ``K`` is 1 with probability exactly 1/2, whatever ``D`` leans to. For
images this holds only approximately: the subband of a flipped image is not exactly the flipped subband (the
wavelet filters' alignment and the borders; they differ by up to ~1 on a 64x48 image whose subband averages ~2), so
fairness on images is a measurement (BENCHMARKS.md, #22: held-out photos, p = 0.27 / 0.93 / 0.91 for 32 / 48 / 64
bits against a fair decoder), not a theorem.

A mark is embedded for ``K`` by giving the wrapped decoder to the embedding
(``gsw.embed(..., decoder=KleinReadout(load_decoder(32)))``) and read by giving it to the reading (``gsw.extract`` /
``gsw.verify``, ``decoder=``); it costs four decoder passes (one batch) per reading. Its weights fingerprint differs
from the wrapped decoder's, so a registry tells its marks apart and the shipped null models (calibrated on the direct
readout) are not applied to it.

Torch-only.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor, nn

__all__ = ["KleinReadout", "shipped_klein_fingerprint"]


class KleinReadout(nn.Module):
    """A decoder read through ``(D(ll) - D(h ll) - D(v ll) + D(r ll)) / 2`` on its LL2 input.

    Args:
        decoder: ``D``, a module mapping LL2 subbands [B, 3, h, w] to logits [B, k]
            (e.g. :func:`gsw.decoder.load_decoder`).

    Attributes:
        inner: the wrapped decoder.
        num_bits: ``k`` (from ``decoder.num_bits`` when it has one, else None).
    """

    def __init__(self, decoder: nn.Module) -> None:
        super().__init__()
        self.inner = decoder
        self.num_bits = getattr(decoder, "num_bits", None)

    def forward(self, ll: Tensor) -> Tensor:
        """ll [B, 3, h, w] -> logits [B, k]: the four orientations decoded as one batch of 4B."""
        h = ll.flip(-1)
        d = self.inner(torch.cat([ll, h, ll.flip(-2), h.flip(-2)])).unflatten(0, (4, ll.shape[0]))
        return (d[0] - d[1] - d[2] + d[3]) / 2.0

    def decode_image(self, images: Tensor) -> Tensor:
        """images [B, 3, H, W] in [0, 1] -> logits [B, k]: their LL2 subband, then :meth:`forward`."""
        from gsw.decoder.dwt import LEVELS, ll_subband

        return self(ll_subband(images, LEVELS))

    @torch.no_grad()
    def bits(self, images: Tensor) -> Tensor:
        """images [B, 3, H, W] in [0, 1] -> bits [B, k] in {0, 1} (float)."""
        return (self.decode_image(images) > 0).float()


@functools.lru_cache(maxsize=None)
def shipped_klein_fingerprint(num_bits: int) -> str:
    """The weights fingerprint (:func:`gsw.decoder.null.decoder_fingerprint`) of ``KleinReadout`` over the shipped
    ``num_bits`` decoder: what a registry records for marks embedded through it, and how ``gsw identify`` /
    ``gsw scan`` recognise them without being given the decoder.

    Raises:
        WeightsError: no shipped decoder of that length.
    """
    from gsw.decoder.null import decoder_fingerprint
    from gsw.decoder.zoo import load_decoder

    return decoder_fingerprint(KleinReadout(load_decoder(num_bits)))
