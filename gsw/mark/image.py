"""`gsw.embed_image` / `gsw.embed_images`: the same watermark in 2-D images (posters, thumbnails, video frames).

The message is written by optimising the image against the frozen decoder that :func:`gsw.extract` and
:func:`gsw.verify` read (:func:`gsw.mark.refine.watermark_images`), so one key proves ownership of a
3DGS model's renders and of the images watermarked here alike.

Example:
    >>> import torch, gsw
    >>> img = torch.rand(3, 64, 64)
    >>> res = gsw.embed_image(img, "key:my-studio", config=gsw.ImageEmbedConfig(steps=2), progress=False)
    >>> res.image.shape, len(res.message_hex)
    (torch.Size([3, 64, 64]), 8)
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from gsw.data.images import to_unit
from gsw.mark.message import MessageLike, as_message, message_to_hex
from gsw.stats import binomial_p_value
from gsw.metrics.image import psnr
from gsw.progress import Progress
from gsw.mark.refine import ImageEmbedConfig

__all__ = ["MIN_SIDE", "ImageEmbedConfig", "ImageEmbedResult", "embed_image", "embed_images"]

#: Smallest image side accepted (the decoder reads the 4x smaller LL2 subband).
MIN_SIDE = 32


@dataclass
class ImageEmbedResult:
    """Result of :func:`embed_image`.

    Attributes:
        image: [3,H,W] watermarked image in [0, 1], already quantised to 8 bits (save it losslessly, e.g. PNG).
        message: [k] embedded bits; ``message_hex`` the same as hex.
        psnr: PSNR (dB) of ``image`` against the input.
        bit_accuracy: share of the message bits the decoder reads back from ``image``.
        p_value: probability that an unmarked image matches at least as many bits (binomial, p = 1/2).
        seconds: wall time of the optimisation.
    """

    image: Tensor
    message: Tensor
    message_hex: str
    psnr: float
    bit_accuracy: float
    p_value: float
    seconds: float


def _check_image(image: Tensor) -> Tensor:
    if not isinstance(image, Tensor):
        raise TypeError(f"image must be a torch.Tensor [3,H,W], got {type(image).__name__}")
    if image.dim() != 3 or image.shape[0] != 3:
        raise ValueError(f"image must be [3,H,W] RGB, got shape {list(image.shape)}")
    if min(image.shape[1:]) < MIN_SIDE:
        raise ValueError(f"image is {image.shape[1]}x{image.shape[2]}; both sides must be >= {MIN_SIDE} pixels")
    if image.dtype == torch.uint8:
        return to_unit(image)
    if not image.is_floating_point():
        raise TypeError(f"image must be uint8 or floating point, got {image.dtype}")
    if not bool(torch.isfinite(image).all()):
        raise ValueError("image contains NaN or infinite values")
    if float(image.min()) < 0.0 or float(image.max()) > 1.0:
        raise ValueError(f"image values must lie in [0, 1], got [{float(image.min()):.3g}, {float(image.max()):.3g}]")
    return image.float()


def _quantise_8bit(images: Tensor) -> Tensor:
    """What a saved 8-bit image holds: each value becomes exactly the float32 nearest to ``k / 255``.

    The codes are divided by :func:`gsw.data.images.to_unit` (a GPU division by the number 255 multiplies by a
    rounded reciprocal and can land one ulp off ``k / 255``; then reading the saved file back, or quantising
    again, would not reproduce the result bit for bit).
    """
    return to_unit((images.float() * 255.0).round().clamp_(0, 255).to(torch.uint8))


def embed_image(image: Tensor, message: MessageLike = None, *, num_bits: int = 32,
                config: ImageEmbedConfig | None = None, decoder: torch.nn.Module | None = None,
                progress: bool = True) -> ImageEmbedResult:
    """Watermarks one image so that :func:`gsw.extract` / :func:`gsw.verify` read ``message`` from it.

    Args:
        image: [3,H,W] RGB in [0, 1] (float) or uint8; both sides >= :data:`MIN_SIDE`.
        message: bits, a hex string, ``"key:<secret>"`` or None (a fresh secret message from the OS entropy
            pool, never from ``config.seed``; the result's ``message`` / ``message_hex`` is the only copy).
        num_bits: message length (32, 48 or 64 with the shipped decoders).
        config: :class:`ImageEmbedConfig` (default settings when None).
        decoder: a custom decoder (LL2 -> logits, as :func:`gsw.decoder.load_decoder` returns); default: the
            shipped one for ``num_bits``.
        progress: show a progress bar on stderr.

    Returns:
        An :class:`ImageEmbedResult`; the input is left untouched.
    """
    return embed_images([image], message, num_bits=num_bits, config=config, decoder=decoder,
                        progress=progress)[0]


def embed_images(images: Sequence[Tensor], message: MessageLike = None, *, num_bits: int = 32,
                 config: ImageEmbedConfig | None = None, decoder: torch.nn.Module | None = None,
                 batch_size: int = 8, progress: bool = True) -> list[ImageEmbedResult]:
    """Watermarks several images with one message, optimising images of the same size together.

    Batches are much faster per image on a GPU (H200: 0.5 s instead of 2.4 s per 481x321 photo at batch 10,
    BENCHMARKS.md 5b). The same images, settings and ``batch_size`` give the same outputs.

    Args:
        images: [3,H,W] images as in :func:`embed_image` (sizes may differ).
        message, num_bits, config, decoder: as in :func:`embed_image`; every image carries the same message.
        batch_size: at most this many same-size images are optimised together (GPU memory grows with it).
        progress: show a progress bar on stderr.

    Returns:
        One :class:`ImageEmbedResult` per image, in input order (``seconds``: the image's share of its batch).
    """
    from gsw.device import resolve_device
    from gsw.mark.detect import load_decoder_for
    from gsw.decoder.dwt import ll_subband
    from gsw.decoder.pretrain.evaluation import same_size_groups
    from gsw.mark.refine import watermark_images

    cfg = config or ImageEmbedConfig()
    if cfg.steps < 0 or cfg.attack_every < 0:
        raise ValueError(f"steps and attack_every must be >= 0, got {cfg.steps} and {cfg.attack_every}")
    if not (cfg.psnr > 0 and cfg.lr > 0):
        raise ValueError(f"psnr and lr must be positive, got {cfg.psnr} and {cfg.lr}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if len(images) == 0:
        raise ValueError("no images given")
    device = resolve_device(cfg.device)
    checked = []
    for i, img in enumerate(images):
        try:
            checked.append(_check_image(img))
        except (TypeError, ValueError) as err:
            raise type(err)(f"image {i}: {err}" if len(images) > 1 else str(err)) from None
    bits = as_message(message, num_bits)  # None: secret (os.urandom); the seed drives the optimisation only
    dec = load_decoder_for(num_bits, decoder, device)
    chunks = same_size_groups(checked, batch_size)
    results: list[ImageEmbedResult | None] = [None] * len(checked)
    hex_message = message_to_hex(bits) if num_bits % 4 == 0 else ""
    with Progress(cfg.steps * len(chunks), "embed-image", enabled=progress) as bar:
        def step(_: int, loss: Tensor) -> None:
            bar.update(**({"loss": f"{float(loss):.4f}"} if bar.due else {}))

        for n, chunk in enumerate(chunks):
            t0 = time.perf_counter()
            x = torch.stack([checked[i] for i in chunk]).to(device)
            y = watermark_images(dec, x, bits.to(device).expand(len(chunk), -1), psnr=cfg.psnr, steps=cfg.steps,
                                 attack_every=cfg.attack_every, lr=cfg.lr, seed=cfg.seed + n,
                                 amp=device.type == "cuda", callback=step)
            y = _quantise_8bit(y)
            seconds = (time.perf_counter() - t0) / len(chunk)
            with torch.no_grad():
                read = (dec(ll_subband(y)) > 0).float().cpu()
            for row, i in enumerate(chunk):
                matches = int((read[row] == bits).sum())
                results[i] = ImageEmbedResult(
                    image=y[row].to(images[i].device), message=bits, message_hex=hex_message,
                    psnr=float(psnr(y[row], x[row])), bit_accuracy=matches / num_bits,
                    p_value=binomial_p_value(matches, num_bits), seconds=seconds)
    return results  # type: ignore[return-value]
