"""Several recipients fine-tuned together on one device: batched parameters, one loss, one Adam.

Every recipient starts from the same FGD'd model (:class:`gsw.fingerprint.shared.WorkerScene`). The
trained parameters of K recipients are stacked into ``[K, N, ...]`` tensors with one Adam and one update
mask over them (both act element-wise, so each recipient gets exactly the update it would get alone).
Per step (one view, the same shuffled order for all K): K renders, then ONE batched pass of the wavelet
transform, decoder, LPIPS and the loss over ``[K, 3, H, W]``. The batched loss is K times the mean of the
per-recipient losses, i.e. their sum, so each recipient's gradient is that of :func:`gsw.mark.embed.embed`
with the same message, views and seed. What batching saves is the per-step fixed cost (small kernels,
launches, Python) of the loss, decoder and optimiser; the renders stay one per recipient.
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch import Tensor

from gsw.gaussians import Gaussians
from gsw.mark.embed import EmbedConfig
from gsw.mark.mask import UpdateMask

__all__ = ["BatchedParams", "CopyResult", "batched_loss", "finetune_batch"]


def _stack(t: Tensor, k: int) -> Tensor:
    return t.detach().unsqueeze(0).repeat(k, *([1] * t.dim())).contiguous().requires_grad_()


class BatchedParams:
    """K recipients' trainable parameters stacked along a leading axis, their Adam and update mask.

    Args:
        model: the shared starting model.
        k: number of recipients.
        cfg: the embedding settings (learning rates, mask kind; positions stay shared while
            ``lr_position`` is 0).
    """

    def __init__(self, model: Gaussians, k: int, cfg: EmbedConfig) -> None:
        self.k = k
        self.means = _stack(model.means, k) if cfg.lr_position > 0 else model.means.detach()
        self.dc = _stack(model.sh[:, :1], k)  # [K, N, 1, 3]
        self.rest = _stack(model.sh[:, 1:], k)  # [K, N, C-1, 3]
        self.logits = _stack(model.opacity_logits, k)  # [K, N]
        self.log_scales = _stack(model.log_scales, k)  # [K, N, 3]
        self.quats = _stack(model.quats, k)  # [K, N, 4]
        groups = [(self.dc, cfg.lr_f_dc), (self.rest, cfg.lr_f_rest), (self.logits, cfg.lr_opacity),
                  (self.log_scales, cfg.lr_scaling), (self.quats, cfg.lr_rotation)]
        masked = [p for p, _ in groups if p.numel() > 0]
        if cfg.lr_position > 0:
            groups.append((self.means, cfg.lr_position))
        self.opt = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in groups if p.numel() > 0], eps=1e-15)
        # the masks of identical stacked copies are the copies' masks (normalised by the same extreme)
        self.mask = UpdateMask(masked, kind=cfg.mask)

    def gaussians(self, j: int) -> Gaussians:
        """Recipient ``j``'s current model (differentiable in its parameters)."""
        means = self.means[j] if self.means.dim() == 3 else self.means
        return Gaussians(means, self.log_scales[j], self.quats[j], self.logits[j],
                         torch.cat([self.dc[j], self.rest[j]], dim=1))


def batched_loss(loss: torch.nn.Module, renders: Tensor, original: Tensor, messages: Tensor,
                 decoded: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The sum over recipients of :class:`gsw.mark.loss.WatermarkLoss`, computed in one batched pass.

    Args:
        loss: the :class:`~gsw.mark.loss.WatermarkLoss` (its decoder, LPIPS network and weights are used).
        renders: [K, 3, H, W] the recipients' renders of one view.
        original: [3, H, W] the input model's render of that view.
        messages: [K, k] the recipients' bits.
        decoded: optional [K, 3, H', W'] images to decode instead of ``renders`` (attacked copies).

    Returns:
        (the summed loss, [K, k] decoder logits).
    """
    from gsw.decoder.dwt import ll_subband
    from gsw.mark.loss import message_loss, subband_l1

    w, k = loss.weights, renders.shape[0]
    target = original.unsqueeze(0).expand_as(renders)
    logits = loss.decoder(ll_subband(renders if decoded is None else decoded))
    # every term is a mean over equally sized samples: K x (batch mean) = sum of the per-recipient terms
    total = (w.l1 * (renders - target).abs().mean() + w.subband * subband_l1(renders, target)
             + w.message * message_loss(logits, messages, loss.logit_scale))
    if loss.lpips is not None:
        total = total + w.lpips * loss.lpips(renders, target).mean()
    return k * total, logits


@dataclass
class CopyResult:
    """One recipient's fine-tuned copy.

    Attributes:
        name: the recipient.
        gaussians: the watermarked model (CPU).
        bit_accuracy: mean over the embedding views of the bits read from the final render.
        min_bit_accuracy: the worst view's.
        psnr: mean PSNR (dB) of the final renders against the original renders.
        min_psnr: the worst view's.
        seconds: this recipient's share of the batch's wall time.
    """

    name: str
    gaussians: Gaussians
    bit_accuracy: float
    min_bit_accuracy: float
    psnr: float
    min_psnr: float
    seconds: float = 0.0


def _attack_layers(cfg: EmbedConfig) -> dict | None:
    if cfg.model_attacks > 0:
        raise ValueError("fingerprinting does not support train-time model attacks (EmbedConfig.model_attacks); "
                         "use gsw embed per recipient for them")
    if cfg.attacks <= 0:
        return None
    from gsw.attacks.layers import training_noise_layers

    return {k: v for k, v in training_noise_layers().items() if k != "identity"}


def finetune_batch(scene, names: Sequence[str], messages: Tensor,
                   on_step: Callable[[int], None] | None = None) -> list[CopyResult]:
    """Fine-tunes one copy per recipient, all together, and scores them on the embedding views.

    Args:
        scene: a :class:`gsw.fingerprint.shared.WorkerScene`.
        names: the K recipients.
        messages: [K, k] their bits.
        on_step: called with K after every optimisation step (progress).

    Returns:
        One :class:`CopyResult` per recipient, in order.
    """
    from gsw.render.rasterize import rasterize

    start = time.perf_counter()
    cfg: EmbedConfig = scene.shared.config
    cams, bg, k = scene.shared.cameras, cfg.background, len(names)
    target = messages.to(scene.device, torch.float32)
    params = BatchedParams(scene.model, k, cfg)
    attacks = _attack_layers(cfg)
    rng, tgen = random.Random(cfg.seed), torch.Generator().manual_seed(cfg.seed)
    for _ in range(cfg.epochs):
        order = list(range(len(cams)))
        rng.shuffle(order)
        for v in order:
            renders = torch.stack([rasterize(params.gaussians(j), cams[v], background=bg, validate=False).image
                                   for j in range(k)])
            decoded = None
            if attacks is not None and rng.random() < cfg.attacks:
                decoded = attacks[rng.choice(sorted(attacks))](renders.clamp(0, 1), generator=tgen)
            total, _ = batched_loss(scene.loss, renders, scene.originals[v], target, decoded)
            params.opt.zero_grad(set_to_none=True)
            total.backward()
            params.mask.step(params.opt)
            if on_step is not None:
                on_step(k)
    copies = [params.gaussians(j).detach() for j in range(k)]
    results = _score(scene, names, copies, target)
    for r in results:
        r.seconds = (time.perf_counter() - start) / k
    return results


@torch.no_grad()
def _score(scene, names: Sequence[str], copies: Sequence[Gaussians], target: Tensor) -> list[CopyResult]:
    """Bit accuracy and PSNR of each copy on every embedding view (decoded in one batch per view)."""
    from gsw.decoder.dwt import ll_subband
    from gsw.metrics.image import psnr
    from gsw.render.rasterize import rasterize

    bg = scene.shared.config.background
    accs, psnrs = [], []
    for cam, orig in zip(scene.shared.cameras, scene.originals):
        imgs = torch.stack([rasterize(g, cam, background=bg).image.clamp(0, 1) for g in copies])
        logits = scene.loss.decoder(ll_subband(imgs))
        accs.append(((logits > 0).float() == target).float().mean(dim=1).cpu())
        psnrs.append(torch.stack([psnr(img, orig.clamp(0, 1)) for img in imgs]).cpu())
    acc, ps = torch.stack(accs, dim=1), torch.stack(psnrs, dim=1)  # [K, views]
    return [CopyResult(n, g.to("cpu"), float(a.mean()), float(a.min()), float(p.mean()), float(p.min()))
            for n, g, a, p in zip(names, copies, acc, ps)]

