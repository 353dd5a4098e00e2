"""Image-space watermarking against a frozen decoder: residual refinement and the optimisation encoder.

:func:`watermark_images` (behind :func:`gsw.embed_image`) writes a message into photos by optimising a residual
that starts as seeded noise with :func:`refine_residual`; every ``attack_every``-th step decodes through the
next training noise layer so the mark survives them.

The 3DGS embedding writes a message by optimising the scene against the frozen decoder; this module does the
same for a single image's residual, starting from a pre-training encoder's output: ``steps`` Adam steps on
the residual, which is kept at a fixed PSNR (rescaled per image) and clamped to the valid range, minimising a
margin loss on the decoder's logits, optionally also through random attacks (expectation over
transformations).

The learned template encoders stop well below what the decoders can read at 64 bits (BENCHMARKS.md section 5a:
96.0 % clean). With the shipped 64-bit decoder, 1,000 steps from noise with the margin at 0 and every 4th step
through a training noise layer read 99.78 % of the bits clean with every layer >= 96.7 % (100 val photos x 4
messages, PSNR 30 dB); a margin of 2 capped the clean accuracy at 99.1-99.3 % however many steps ran.

Example:
    >>> import torch
    >>> from gsw.decoder.hidden import HiddenDecoder
    >>> dec = HiddenDecoder(8, num_blocks=1, channels=8).eval()
    >>> x, m = torch.rand(2, 3, 32, 32), torch.randint(0, 2, (2, 8)).float()
    >>> refine_residual(dec, x, torch.randn_like(x), m, psnr=30.0, steps=2).shape
    torch.Size([2, 3, 32, 32])
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from gsw.decoder.dwt import ll_subband
from gsw.decoder.hidden import scale_to_psnr
from gsw.attacks.layers import TRAINING_LAYER_NAMES, GpuAttacks

__all__ = ["ATTACKS", "SCHEDULES", "ImageEmbedConfig", "attack_cycle", "refine_residual", "scale_to_psnr",
           "watermark_images"]

#: Learning-rate schedules of :func:`refine_residual`.
SCHEDULES = ("cosine", "constant")


def attack_cycle(
    apply: Callable[[str, torch.Tensor, float], torch.Tensor], names: Sequence[str], every: int = 1
) -> Callable[[torch.Tensor, int], torch.Tensor | None]:
    """An ``attack`` for :func:`refine_residual`: the named attacks in turn, on every ``every``-th step.

    Args:
        apply: (name, images [B,3,H,W], strength) -> attacked images, differentiable (for instance
            ``gsw.attacks.layers.GpuAttacks(device, seed).apply``); called at strength 1.
        names: the attacks, cycled in this order.
        every: steps ``0, every, 2 every, ...`` go through the next attack; the others return None (clean).
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    if not names:
        raise ValueError("names must not be empty")

    def attack(y: torch.Tensor, step: int) -> torch.Tensor | None:
        if step % every:
            return None
        return apply(names[(step // every) % len(names)], y, 1.0)

    return attack


def refine_residual(
    decoder: Callable[[torch.Tensor], torch.Tensor],
    images: torch.Tensor,
    residual: torch.Tensor,
    msgs: torch.Tensor,
    psnr: float,
    steps: int = 100,
    lr: float = 0.3,
    margin: float = 0.0,
    attack: Callable[[torch.Tensor, int], torch.Tensor] | None = None,
    amp: bool = False,
    schedule: str = "cosine",
    callback: Callable[[int, torch.Tensor], None] | None = None,
) -> torch.Tensor:
    """Refine ``residual`` so that ``decoder`` reads ``msgs`` from the watermarked images.

    Args:
        decoder: LL2 subband [B,3,h,w] -> logits [B,k] (eval mode; its parameters get no gradient).
        images: [B,3,H,W] in [0, 1], the cover images.
        residual: [B,3,H,W] starting residual (any scale: it is rescaled to ``psnr``).
        msgs: [B,k] in {0, 1}.
        psnr: PSNR (dB) of the watermarked image before clamping, kept at every step.
        steps: Adam steps (0 returns the start, rescaled and clamped).
        lr: Adam learning rate, in the units of a residual at RMS 1 (the residual is rescaled after each
            step, so this sets how far each step turns it).
        margin: the loss is softplus(margin - s * logit), s = +-1 the target bit (0: binary cross-entropy).
            A positive margin keeps pushing bits that are already right; measured at 64 bits it costs clean
            accuracy (margin 2: 99.3 %, 0: 99.8 %) and buys no robustness over the attacks.
        attack: optional (images [B,3,H,W], step) -> attacked images, differentiable: the loss is then the
            mean of the clean images' and the attacked images' (one random attack per step, for instance);
            returning None keeps that step's loss clean.
        amp: run the decoder under bfloat16 autocast (CUDA: about twice as fast; the result is still
            float32).
        schedule: ``"cosine"`` (lr decays to 0 over the steps) or ``"constant"``.
        callback: called after every step with (step, loss) (a detached scalar tensor; reading it on a GPU
            synchronises, so read it only when needed).

    Returns:
        [B,3,H,W] watermarked images in [0, 1] (not quantised).
    """
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    if schedule not in SCHEDULES:
        raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
    images = images.float()
    r = scale_to_psnr(residual.detach().float(), 0.0).requires_grad_(True)  # RMS 1: the units of ``lr``
    opt = torch.optim.Adam([r], lr=lr)
    sign = msgs.float() * 2.0 - 1.0
    with torch.enable_grad():
        for step in range(steps):
            y = (images + scale_to_psnr(r, psnr)).clamp(0.0, 1.0)
            attacked = None if attack is None else attack(y, step)
            views = [y] if attacked is None else [y, attacked]
            loss = 0.0
            for v in views:
                with torch.autocast(images.device.type, dtype=torch.bfloat16, enabled=amp):
                    logits = decoder(ll_subband(v))
                loss = loss + F.softplus(margin - sign * logits.float()).mean() / len(views)
            (r.grad,) = torch.autograd.grad(loss, r)
            if schedule == "cosine":
                opt.param_groups[0]["lr"] = lr * 0.5 * (1.0 + math.cos(math.pi * step / steps))
            opt.step()
            if callback is not None:
                callback(step, loss.detach())
    return (images + scale_to_psnr(r.detach(), psnr)).clamp(0.0, 1.0)

#: The training noise layers cycled through during the optimisation ("identity" = a clean step).
ATTACKS: tuple[str, ...] = TRAINING_LAYER_NAMES


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
            :class:`~gsw.decoder.zoo.WatermarkDecoder` (what :func:`gsw.extract` reads) or its raw
            ``.decoder``.
        images: [B,3,H,W] cover images in [0, 1] (any size the decoder accepts).
        msgs: [B,k] bits in {0, 1}.
        psnr: PSNR (dB) of the residual before clamping (the saved image's PSNR is within ~0.1 dB of it).
        steps: Adam steps (0: seeded noise at that PSNR, which carries no message).
        attack_every: every this many steps also go through the next of :data:`ATTACKS` (0: clean loss only,
            measured less robust: BENCHMARKS.md section 5a).
        lr: Adam learning rate, in units of a residual at RMS 1.
        margin, schedule: as in :func:`~gsw.mark.refine.refine_residual` (the defaults, binary
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
