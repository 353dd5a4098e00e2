"""`gsw.extract` and `gsw.verify`: reading the 3D-GSW watermark from images or renders of a model.

:func:`extract` decodes the bits of images with the frozen decoder; :func:`verify` tests images (or the renders of a
model) for a claimed message with :func:`gsw.mark.evidence.assess`: for a random message (gsw's default, or
``key:<secret>``) the exact randomization test of :mod:`gsw.mark.randomization` (exact over the random draw of the
message, for any image and any number of correlated frames); for a message someone chose (``origin="chosen"``) the
decoder's calibrated null model. :func:`message_num_bits` is the one rule that infers a message's length.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence, Union

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.gaussians import Gaussians
from gsw.mark.message import MessageLike, as_message, message_to_hex
from gsw.render.rasterize import rasterize
from gsw.stats import DETECTION_FPR

__all__ = ["Extraction", "ImageLike", "Verdict", "extract", "load_decoder_for", "message_num_bits", "verify"]


def load_decoder_for(num_bits: int, decoder: torch.nn.Module | None, device: torch.device) -> torch.nn.Module:
    """The frozen decoder of ``num_bits`` on ``device``: the shipped one, or ``decoder`` checked to read
    ``num_bits`` from an LL2 subband.

    Raises:
        ValueError: ``decoder`` does not output ``[1, num_bits]`` for one image.
    """
    if decoder is None:
        from gsw.decoder.zoo import load_decoder

        return load_decoder(num_bits).to(device).eval().requires_grad_(False)
    from gsw.decoder.dwt import ll_subband

    decoder = decoder.to(device).eval().requires_grad_(False)
    with torch.no_grad():  # a custom decoder must read num_bits from an LL2 subband
        out = decoder(ll_subband(torch.zeros(1, 3, 64, 64, device=device)))
    if out.dim() != 2 or out.shape[-1] != num_bits:
        raise ValueError(f"the decoder outputs shape {list(out.shape)} for one image; expected [1, {num_bits}] "
                         f"(num_bits={num_bits})")
    return decoder


def message_num_bits(message: MessageLike) -> int:
    """The length of a message given as bits or hex (4 bits per hex digit, ``0x`` optional).

    Args:
        message: a hex string or a sequence/tensor of bits (not a key, not None: their length is a choice).

    Returns:
        The number of bits.

    Raises:
        ValueError: a key string or None (pass ``num_bits``).
    """
    if message is None or (isinstance(message, str) and message.startswith("key:")):
        raise ValueError("num_bits is required for a key or a missing message")
    if isinstance(message, str):
        return 4 * len(message.lower().removeprefix("0x"))
    return int(torch.as_tensor(message).numel())


@dataclass
class Extraction:
    """Bits read from images.

    Attributes:
        bits: [B, k] decoded bits (1 where the logit is positive).
        logits: [B, k] whitened decoder logits (soft scores).
    """

    bits: Tensor
    logits: Tensor

    @property
    def hex(self) -> list[str]:
        """Hex string per image (k a multiple of 4)."""
        return [message_to_hex(b) for b in self.bits]


ImageLike = Union[Tensor, Sequence[Tensor]]


def _as_images(images: ImageLike) -> list[Tensor]:
    """[1,3,H,W] tensors in [0, 1], one per image (sizes may differ)."""
    if isinstance(images, Tensor):
        batch = images.unsqueeze(0) if images.dim() == 3 else images
        if batch.dim() != 4 or batch.shape[1] != 3:
            raise ValueError(f"expected [3,H,W] or [B,3,H,W] RGB images, got shape {list(batch.shape)}")
        return [img[None].float().clamp(0, 1) for img in batch]
    out = []
    for i, img in enumerate(images):
        if not isinstance(img, Tensor) or img.dim() != 3 or img.shape[0] != 3:
            shape = list(img.shape) if isinstance(img, Tensor) else type(img).__name__
            raise ValueError(f"image {i}: expected a [3,H,W] RGB tensor, got {shape}")
        out.append(img[None].float().clamp(0, 1))
    if not out:
        raise ValueError("no images given")
    return out


@torch.no_grad()
def extract(images: ImageLike, *, num_bits: int = 32, decoder: torch.nn.Module | None = None,
            embed_size: tuple[int, int] | None = None) -> Extraction:
    """Reads the watermark bits from one or more images (e.g. screenshots of renders).

    Args:
        images: [3, H, W], [B, 3, H, W] or a list of [3, H, W] RGB images in [0, 1] (sizes may differ).
        num_bits: message length of the decoder.
        decoder: a custom decoder (LL2 subband -> logits); default: the shipped one for `num_bits`.
        embed_size: ``(height, width)`` of the embedding renders, when known (a model's ``watermark.json``,
            the registry): every image is resized to it before decoding, as :func:`verify` reads it
            (:func:`gsw.mark.scales.read_plan`). None: each image is read as given. Without a claimed
            message there is no p-value to pay for a scale search, so extract never searches.

    Returns:
        An :class:`Extraction`.
    """
    from gsw.mark.scales import read_images

    imgs = [img[0] for img in _as_images(images)]
    dec = load_decoder_for(num_bits, decoder, imgs[0].device)
    readings = read_images(imgs, dec, embed_size=embed_size, factors=(1.0,))
    logits = torch.stack([r.logits[0] for r in readings]).to(imgs[0].device)
    return Extraction((logits > 0).float(), logits)


@dataclass
class Verdict:
    """Ownership test of images against a message.

    Attributes:
        bit_accuracy: per image, fraction of matching bits.
        matches: per image, number of matching bits.
        p_values: per image, the p-value of its evidence (random message: the exact randomization test of
            its most confident reading; chosen message: the decoder's calibrated null model, the scale search
            counted in).
        p_value: combined over images, valid for correlated frames (:func:`gsw.mark.evidence.assess`).
        test: the test behind the p-values: ``"exact"`` (random message), ``"calibrated"`` (chosen message, the
            decoder's null model) or ``"fair"`` (chosen message, fair coin: a decoder without a null model, e.g.
            :class:`gsw.decoder.KleinReadout`, whose bits are fair per bit by symmetry but whose bit correlations
            are not accounted for).
    """

    bit_accuracy: list[float]
    matches: list[int]
    p_values: list[float]
    p_value: float
    test: str = "exact"

    def detected(self, fpr: float = DETECTION_FPR) -> bool:
        """Whether the combined p-value is at or below `fpr`."""
        return self.p_value <= fpr


@torch.no_grad()
def verify(source: ImageLike | tuple[Gaussians, Sequence[Camera]], message: MessageLike, *,
           num_bits: int | None = None, decoder: torch.nn.Module | None = None,
           background: tuple[float, float, float] = (0.0, 0.0, 0.0),
           embed_size: tuple[int, int] | None = None, origin: str = "random") -> Verdict:
    """Tests images (or renders of a model) for a given message.

    Args:
        source: images ([3,H,W], [B,3,H,W] or a list) or a `(gaussians, cameras)` pair to render.
        message: the claimed message (bits, hex or `"key:<secret>"`).
        num_bits: message length (inferred from bits/hex when omitted, :func:`message_num_bits`;
            required for keys).
        decoder: a custom decoder.
        background: render background for a model source.
        embed_size: ``(height, width)`` of the embedding renders when known (read at that size only);
            otherwise a documented set of scales is searched, counted in the p-value.
        origin: ``"random"`` (default): the message was drawn uniformly at random independently of the
            images (gsw's default messages, ``key:<secret>``), and the p-value is exact over that draw;
            ``"chosen"``: someone picked it (e.g. ``gsw embed --message HEX``), tested against the
            decoder's calibrated null model instead (:func:`gsw.mark.evidence.assess`).

    Returns:
        A :class:`Verdict`.
    """
    if num_bits is None:
        num_bits = message_num_bits(message)
    bits = as_message(message, num_bits)
    if isinstance(source, tuple) and len(source) == 2 and isinstance(source[0], Gaussians):
        g, cams = source
        images = [rasterize(g, cam, background=background).image for cam in cams]
    else:
        images = source
    from gsw.mark.evidence import assess

    ev = assess([img[0] for img in _as_images(images)], bits, num_bits=num_bits, decoder=decoder,
                embed_size=embed_size, origin=origin)
    return Verdict(ev.bit_accuracy, ev.matches, ev.p_values, ev.p_value, ev.null_model)
