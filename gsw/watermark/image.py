"""Image-space watermarking against a frozen decoder: an optimisation encoder.

A message is written into a photo by optimising a residual against the frozen decoder (Fernandez et al.'s
"watermarking in a latent space" recipe, applied to the HiDDeN decoder): the residual starts as seeded noise
and takes ``steps`` Adam steps of :func:`~gsw.watermark.refine.refine_residual` (binary cross-entropy, the
residual kept at a fixed PSNR and clamped to [0, 1]); every ``attack_every``-th step also decodes the image
through the next training noise layer (crop, resize, JPEG, blur, noise, rotation, combined), so the watermark
survives them.  This is the image-space analogue of the 3DGS embedding; measured as the encoder of the
pre-training pair it reads 100 % of 32 / 48 / 64 bits clean against the shipped decoders, where the learned
HiDDeN encoder stops at 96 % for 64 bits (BENCHMARKS.md sections 5, 5b).

Example:
    >>> import torch
    >>> from gsw.watermark.hidden import HiddenDecoder
    >>> dec = HiddenDecoder(8, num_blocks=1, channels=8).eval()
    >>> x, m = torch.rand(2, 3, 32, 32), torch.randint(0, 2, (2, 8)).float()
    >>> watermark_images(dec, x, m, psnr=30.0, steps=2).shape
    torch.Size([2, 3, 32, 32])
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from .refine import attack_cycle, refine_residual
from .training import GpuAttacks, MultiConfig

__all__ = ["ATTACKS", "ImageEmbedConfig", "watermark_images"]

#: The training noise layers cycled through during the optimisation ("identity" = a clean step).
ATTACKS: tuple[str, ...] = MultiConfig.noise_layers


@dataclass
class ImageEmbedConfig:
    """Settings of :func:`gsw.embed_image` (the defaults measured in BENCHMARKS.md section 5b).

    Attributes:
        psnr: PSNR (dB) of the watermark against the input image.
        steps: Adam steps of the optimisation (time is linear in it).
        attack_every: every this many steps also decode through a training attack (crop, resize, JPEG, blur,
            noise, rotation, combined) so the watermark survives them; 0 optimises for clean copies only.
        lr: Adam learning rate (cosine decay).
        seed: starting noise and attack draws (same seed, same output).
        device: where to optimise ("auto": CUDA when available).
    """

    psnr: float = 36.0
    steps: int = 300
    attack_every: int = 4
    lr: float = 0.3
    seed: int = 0
    device: str = "auto"


def watermark_images(
    decoder: Callable[[torch.Tensor], torch.Tensor],
    images: torch.Tensor,
    msgs: torch.Tensor,
    *,
    psnr: float,
    steps: int = 1000,
    attack_every: int = 4,
    lr: float = 0.3,
    margin: float = 0.0,
    schedule: str = "cosine",
    seed: int = 0,
    amp: bool = False,
    callback: Callable[[int, torch.Tensor], None] | None = None,
) -> torch.Tensor:
    """Write ``msgs`` into ``images`` so that ``decoder`` reads them, at a fixed PSNR.

    Args:
        decoder: LL2 subband [B,3,h,w] -> logits [B,k] (frozen, eval mode), e.g. a shipped
            :class:`~gsw.watermark.zoo.WatermarkDecoder` (what :func:`gsw.extract` reads) or its raw
            ``.decoder``.
        images: [B,3,H,W] cover images in [0, 1] (any size the decoder accepts).
        msgs: [B,k] bits in {0, 1}.
        psnr: PSNR (dB) of the residual before clamping (the saved image's PSNR is within ~0.1 dB of it).
        steps: Adam steps (0: seeded noise at that PSNR, which carries no message).
        attack_every: every this many steps also go through the next of :data:`ATTACKS` (0: clean loss only,
            measured less robust: BENCHMARKS.md section 5a).
        lr: Adam learning rate, in units of a residual at RMS 1.
        margin, schedule: as in :func:`~gsw.watermark.refine.refine_residual` (the defaults, binary
            cross-entropy and a cosine decay, are the measured best).
        seed: starting noise and attack draws (the same seed gives the same image).
        amp: decode under bfloat16 autocast (CUDA).
        callback: (step, loss) after every step (progress bars).

    Returns:
        [B,3,H,W] watermarked images in [0, 1] (float, not yet quantised to 8 bits).
    """
    if attack_every < 0:
        raise ValueError(f"attack_every must be >= 0, got {attack_every}")
    gen = torch.Generator(device=images.device).manual_seed(seed)
    start = torch.randn(images.shape, device=images.device, generator=gen)
    attack = attack_cycle(GpuAttacks(images.device, seed + 1).apply, ATTACKS, attack_every) if attack_every else None
    return refine_residual(decoder, images, start, msgs, psnr, steps, lr, margin, attack, amp=amp,
                           schedule=schedule, callback=callback)
