"""Reading the watermark at the scale it was embedded at.

The decoder reads the level-2 LL subband, so it expects the content at the pixel scale of the embedding:
a render at 2x the embedding resolution, or a screenshot shown at half size, shifts the message out of
that band.  Two ways to read an image:

* **embedding size known** (e.g. from the model folder's cameras): the image is resized to that size
  (:func:`read_plan` with ``embed_size``) and read once -- no search, no multiple-testing penalty;
* **unknown**: the image is read at every factor of :data:`SEARCH_FACTORS` whose read fits
  :data:`MIN_READ_SIDE` .. :data:`MAX_READ_SIDE`; :mod:`gsw.mark.evidence` keeps the reading with the
  smallest weighted p-value and pays for the search in a weighted Bonferroni
  (:func:`gsw.mark.evidence.reading_weights`, :func:`gsw.stats.bonferroni_p_value`).

Resizing is :func:`gsw.data.images.resize_image` (area averaging for integer downscales, antialiased
bilinear otherwise, bilinear when enlarging).  Images of one shape are resized and decoded as one batch.

Example:
    >>> [round(f, 3) for f, _ in read_plan(240, 320)]
    [1.0, 0.667, 0.5, 0.333, 2.0]
    >>> read_plan(240, 320, embed_size=(120, 160))
    [(0.5, (120, 160))]
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from gsw.data.images import resize_image, to_unit
from gsw.decoder.pretrain.evaluation import same_size_groups

__all__ = ["SEARCH_FACTORS", "MIN_READ_SIDE", "MAX_READ_SIDE", "Reading", "read_plan", "read_images"]

#: Resize factors of the scale search, in the order they are tried: the image as given, then the
#: content of a render at 1.5x, 2x and 3x the embedding resolution brought back to it, then a render at
#: half the resolution enlarged 2x.
SEARCH_FACTORS: tuple[float, ...] = (1.0, 2.0 / 3.0, 0.5, 1.0 / 3.0, 2.0)
#: Reads whose shorter side would fall below this many pixels are skipped (the LL2 subband the decoder
#: reads is 4x smaller).
MIN_READ_SIDE = 64
#: Reads whose longer side would exceed this many pixels are skipped (enlarging a large image costs 4x
#: the decoding time of the image itself and is rarely the right scale).
MAX_READ_SIDE = 1024
#: Relative aspect-ratio difference up to which an image is read at exactly the embedding size.
ASPECT_TOLERANCE = 0.02


@dataclass
class Reading:
    """The decoder's output for one image at each scale it was read at.

    Attributes:
        factors: [S] resize factors (read size / image size).
        sizes: [S] read sizes ``(height, width)``.
        logits: [S, k] whitened decoder logits (bit = logit > 0), on the CPU.
    """

    factors: list[float]
    sizes: list[tuple[int, int]]
    logits: Tensor

    @property
    def bits(self) -> Tensor:
        """[S, k] decoded bits in {0, 1} (float)."""
        return (self.logits > 0).float()

    @property
    def confidence(self) -> Tensor:
        """[S] mean |logit| of each reading: a message-free sign of the scale a watermark was embedded at
        (it peaks there on marked images), for reading bits without a claimed message."""
        return self.logits.abs().mean(-1)


def _check_size(size: object, name: str) -> tuple[int, int]:
    if (not isinstance(size, (tuple, list)) or len(size) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)):
        raise ValueError(f"{name} must be a (height, width) pair of positive ints, got {size!r}")
    return int(size[0]), int(size[1])


def read_plan(height: int, width: int, *, embed_size: tuple[int, int] | None = None,
              factors: Sequence[float] = SEARCH_FACTORS) -> list[tuple[float, tuple[int, int]]]:
    """The readings of an image of ``height x width``: ``(factor, (read_height, read_width))`` each.

    Args:
        height, width: image size, pixels.
        embed_size: ``(height, width)`` of the embedding renders when known: one reading at that size when
            the aspect ratio agrees within :data:`ASPECT_TOLERANCE`, else at the factor that gives the same
            pixel count (aspect kept). Not limited by :data:`MIN_READ_SIDE` / :data:`MAX_READ_SIDE`.
        factors: the search factors (used when ``embed_size`` is None); factors whose read would have a
            side below :data:`MIN_READ_SIDE` or above :data:`MAX_READ_SIDE` are left out, except the
            first one, which is always read (so every image gets at least one reading).

    Returns:
        the readings, in the order of ``factors``.
    """
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height}x{width}")
    if embed_size is not None:
        eh, ew = _check_size(embed_size, "embed_size")
        if abs((width / height) / (ew / eh) - 1.0) <= ASPECT_TOLERANCE:
            return [(math.sqrt(ew * eh / (width * height)), (eh, ew))]
        f = math.sqrt(ew * eh / (width * height))
        return [(f, (max(1, round(height * f)), max(1, round(width * f))))]
    if len(factors) == 0 or any(not (f > 0 and math.isfinite(f)) for f in factors):
        raise ValueError(f"factors must be positive finite numbers, got {list(factors)}")
    plan = []
    for i, f in enumerate(factors):
        size = (max(1, round(height * f)), max(1, round(width * f)))
        if i == 0 or (min(size) >= MIN_READ_SIDE and max(size) <= MAX_READ_SIDE):
            plan.append((float(f), size))
    return plan


def _as_image_list(images: Tensor | Sequence[Tensor]) -> list[Tensor]:
    if isinstance(images, Tensor):
        if images.dim() == 3:
            images = images[None]
        if images.dim() != 4 or images.shape[1] != 3:
            raise ValueError(f"expected [3,H,W] or [B,3,H,W] RGB images, got shape {list(images.shape)}")
        return list(images)
    out = list(images)
    if not out:
        raise ValueError("no images given")
    for i, img in enumerate(out):
        if not isinstance(img, Tensor) or img.dim() != 3 or img.shape[0] != 3:
            shape = list(img.shape) if isinstance(img, Tensor) else type(img).__name__
            raise ValueError(f"image {i}: expected a [3,H,W] RGB tensor, got {shape}")
    return out


@torch.no_grad()
def _decode(decoder: torch.nn.Module, images: torch.Tensor) -> torch.Tensor:
    """Logits [B, k] of images [B, 3, H, W]: ``decode_image`` when the decoder has it, else decoder(LL2)."""
    if hasattr(decoder, "decode_image"):
        return decoder.decode_image(images)
    from gsw.decoder.dwt import ll_subband

    return decoder(ll_subband(images))


def read_images(images: Tensor | Sequence[Tensor], decoder: torch.nn.Module, *,
                embed_size: tuple[int, int] | None = None, factors: Sequence[float] = SEARCH_FACTORS,
                batch_size: int = 16) -> list[Reading]:
    """Decodes every image at each reading of :func:`read_plan`.

    Args:
        images: [3, H, W] RGB images in [0, 1] (a list, sizes may differ, or a [B, 3, H, W] batch);
            uint8 images (0..255) are moved to the decoder's device as they are and divided by 255 there
            (:func:`gsw.data.images.to_unit`).
        decoder: a module with ``decode_image(images [B,3,H,W]) -> logits [B,k]``
            (:class:`gsw.decoder.zoo.WatermarkDecoder`), or a custom one mapping the LL2 subband to logits.
        embed_size: ``(height, width)`` of the embedding renders, if known (one reading per image).
        factors: search factors when ``embed_size`` is None.
        batch_size: at most this many images of one shape are decoded together.

    Returns:
        one :class:`Reading` per image, in order.
    """
    imgs = _as_image_list(images)
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    param = next(decoder.parameters(), None)
    device = imgs[0].device if param is None else param.device
    plans = [read_plan(int(im.shape[1]), int(im.shape[2]), embed_size=embed_size, factors=factors)
             for im in imgs]
    logits: list[list[Tensor | None]] = [[None] * len(p) for p in plans]
    for group in same_size_groups(imgs, batch_size):
        # each image moved as it is (uint8 is a quarter of float32's bytes), then made float32 on the device
        x = torch.stack([to_unit(imgs[i].to(device)) for i in group])
        h, w = x.shape[-2:]
        # images of one shape share their plan; one resize + decode per reading for the whole group
        for s, (_, size) in enumerate(plans[group[0]]):
            y = resize_image(x, *size) if size != (h, w) else x
            out = _decode(decoder, y).float().cpu()
            for j, i in enumerate(group):
                logits[i][s] = out[j]
    return [Reading([f for f, _ in p], [s for _, s in p], torch.stack(lg))  # type: ignore[arg-type]
            for p, lg in zip(plans, logits)]
