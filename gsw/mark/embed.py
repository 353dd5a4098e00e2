"""`gsw.embed`, `gsw.extract`, `gsw.verify`: the 3D-GSW watermark on a trained 3DGS model.

Pipeline of :func:`embed`: render the original model from every training view (the targets), FGD
phase 1 (prune) and phase 2 (split), then fine-tune the SH colours, opacities, scales and rotations
(positions frozen by default) with Adam, one shuffled view per step, against
:class:`~gsw.mark.loss.WatermarkLoss`, with the gradient mask applied to the updates
(:mod:`gsw.gradient_mask`). Optional train-time attack sampling decodes an attacked copy of the
render (noise, crop, JPEG, blur, rotation, scaling) to harden the watermark.
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass, field
from typing import Sequence, Union

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.mark.fgd import PRUNE_THRESHOLD, TOP_PERCENT, PruneReport, SplitReport, fgd_prune, fgd_split
from gsw.gaussians import Gaussians
from gsw.mark.mask import UpdateMask
from gsw.mark.loss import LossWeights, WatermarkLoss
from gsw.mark.message import (MessageLike, as_message,
                          message_to_hex)
from gsw.metrics.image import psnr
from gsw.render.rasterize import rasterize
from gsw.progress import Progress
from gsw.stats import DETECTION_FPR, binomial_p_value, fisher_combined_p_value


@dataclass
class EmbedConfig:
    """Settings of :func:`embed` (defaults: the paper's recipe; learning rates of the official code except
    the SH colours: f_dc x2 and f_rest x8, measured best with the shipped decoders, BENCHMARKS.md §6).

    Attributes:
        epochs: passes over the shuffled training views.
        lr_f_dc, lr_f_rest, lr_opacity, lr_scaling, lr_rotation, lr_position: Adam learning rates
            (position 0 = frozen, as in the paper).
        weights: loss weights.
        logit_scale: factor on the decoder logits inside the message BCE (the official code: 10).
        lpips_net: "vgg", "alex" or None (no LPIPS term; set weights.lpips = 0).
        mask: "exp" (3D-GSW), "stega" (StegaNeRF-style) or "none".
        fgd: run FGD (prune + split) before fine-tuning.
        prune_threshold: FGD phase-1 threshold on the normalised contribution (:func:`gsw.mark.fgd.fgd_prune`).
        top_percent: FGD phase-2 share of patches (percent).
        split_quantile: FGD phase-2 low-contribution quantile that is split.
        attacks: train-time attack sampling: probability of decoding an attacked render.
        model_attacks: train-time model-attack sampling: probability of decoding the render of a perturbed
            copy of the model instead (Gaussian noise of std ``model_noise`` on every raw parameter but
            the positions, or the SH reduced to degree 0, each half of the time); fidelity losses stay on
            the unperturbed render.  Combines with ``attacks`` (the image attack then hits that render).
        model_noise: std of that parameter noise.
        background: render background.
        seed: RNG seed (view order, attacks).
    """

    epochs: int = 8
    lr_f_dc: float = 5e-3  # official code: 2.5e-3
    lr_f_rest: float = 1e-3  # official code: 1.25e-4
    lr_opacity: float = 0.05
    lr_scaling: float = 5e-3
    lr_rotation: float = 1e-3
    lr_position: float = 0.0
    weights: LossWeights = field(default_factory=LossWeights)
    logit_scale: float = 1.0
    lpips_net: str | None = "vgg"
    mask: str = "exp"
    fgd: bool = True
    prune_threshold: float = PRUNE_THRESHOLD
    top_percent: float = TOP_PERCENT
    split_quantile: float = 0.5
    attacks: float = 0.0
    model_attacks: float = 0.0
    model_noise: float = 0.1
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0


@dataclass
class EmbedResult:
    """Result of :func:`embed`.

    Attributes:
        gaussians: the watermarked model (detached, on the input device).
        message: [k] embedded bits; `message_hex` the same as hex.
        prune, split: FGD reports (None when FGD is off).
        timings: seconds per phase ("renders", "fgd", "finetune", "evaluate", "total").
        bit_accuracy: per training view, fraction of message bits decoded from the final render.
        psnr: per training view, PSNR (dB) of the final render against the original render.
        history: per step loss terms and bit accuracy.
    """

    gaussians: Gaussians
    message: Tensor
    message_hex: str
    prune: PruneReport | None
    split: SplitReport | None
    timings: dict[str, float]
    bit_accuracy: list[float]
    psnr: list[float]
    history: list[dict[str, float]]


def _perturbed(g: Gaussians, rng: random.Random, tgen: torch.Generator, sigma: float) -> Gaussians:
    """A differentiable model attack for train-time sampling, one of two at random: N(0, sigma^2) on every
    raw parameter but the positions, or the view-dependent SH dropped (degree 0).  The evaluation's
    :func:`gsw.attacks.model.parameter_noise_attributes` / :func:`gsw.attacks.model.reduce_sh` return detached copies;
    these keep the graph so the clean parameters learn a message that survives them."""
    if rng.random() < 0.5:
        def noisy(t: Tensor) -> Tensor:
            return t + sigma * torch.randn(t.shape, generator=tgen).to(device=t.device, dtype=t.dtype)

        return Gaussians(g.means, noisy(g.log_scales), noisy(g.quats), noisy(g.opacity_logits), noisy(g.sh))
    return Gaussians(g.means, g.log_scales, g.quats, g.opacity_logits,
                     torch.cat([g.sh[:, :1], torch.zeros_like(g.sh[:, 1:])], dim=1))


def _load_decoder(num_bits: int, decoder: torch.nn.Module | None, device: torch.device) -> torch.nn.Module:
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


def _sample_attack(gen: random.Random, attacks: dict, render: Tensor, tgen: torch.Generator) -> Tensor:
    name = gen.choice(sorted(attacks))
    return attacks[name](render.unsqueeze(0), generator=tgen)[0]


def embed(gaussians: Gaussians, cameras: Sequence[Camera], *, message: MessageLike = None,
          num_bits: int = 32, images: Sequence[Tensor] | None = None,
          config: EmbedConfig | None = None, decoder: torch.nn.Module | None = None,
          progress: bool = True) -> EmbedResult:
    """Embeds an N-bit message into every rendered view of a 3DGS model.

    Args:
        gaussians: the trained model (not modified).
        cameras: its training views.
        message: None (random), bits, a hex string or `"key:<secret>"` (see
            :func:`gsw.mark.message.as_message`).
        num_bits: message length (32, 48 or 64 with the shipped decoders).
        images: optional [3, H, W] training images, used by FGD phase 1's error weighting.
        config: :class:`EmbedConfig`.
        decoder: a custom frozen decoder (LL2 subband -> logits); default: the shipped one.
        progress: show a progress bar on stderr.

    Returns:
        An :class:`EmbedResult`.
    """
    cfg = config or EmbedConfig()
    if len(cameras) == 0:
        raise ValueError("embed needs at least one camera")
    for name in ("attacks", "model_attacks"):
        if not 0.0 <= getattr(cfg, name) <= 1.0:
            raise ValueError(f"EmbedConfig.{name} is a probability in [0, 1], got {getattr(cfg, name)}")
    if cfg.model_noise < 0:
        raise ValueError(f"EmbedConfig.model_noise must be >= 0, got {cfg.model_noise}")
    gaussians.check_finite()
    bits = as_message(message, num_bits, seed=cfg.seed if message is None else None)
    device = gaussians.device
    dec = _load_decoder(num_bits, decoder, device)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    bg = cfg.background

    with torch.no_grad():
        originals = [rasterize(gaussians, cam, background=bg).image for cam in cameras]
    timings["renders"] = time.perf_counter() - start

    t0 = time.perf_counter()
    prune = split = None
    model = gaussians.detach().clone()
    if cfg.fgd:
        model, prune = fgd_prune(model, cameras, images, threshold=cfg.prune_threshold, background=bg)
        model, split = fgd_split(model, cameras, top_percent=cfg.top_percent,
                                 low_quantile=cfg.split_quantile, background=bg)
    timings["fgd"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    means = model.means.clone().requires_grad_(cfg.lr_position > 0)
    dc = model.sh[:, :1].clone().requires_grad_()
    rest = model.sh[:, 1:].clone().requires_grad_()
    logits = model.opacity_logits.clone().requires_grad_()
    log_scales = model.log_scales.clone().requires_grad_()
    quats = model.quats.clone().requires_grad_()
    groups = [(dc, cfg.lr_f_dc), (rest, cfg.lr_f_rest), (logits, cfg.lr_opacity),
              (log_scales, cfg.lr_scaling), (quats, cfg.lr_rotation)]
    if cfg.lr_position > 0:
        groups.append((means, cfg.lr_position))
    trainable = [p for p, _ in groups if p.numel() > 0]
    opt = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in groups if p.numel() > 0], eps=1e-15)
    mask = UpdateMask([p for p in trainable if p is not means], kind=cfg.mask)
    loss_fn = WatermarkLoss(dec, cfg.weights, cfg.lpips_net, cfg.logit_scale).to(device)
    attacks = None
    if cfg.attacks > 0:
        from gsw.attacks.layers import training_noise_layers

        attacks = {k: v for k, v in training_noise_layers().items() if k != "identity"}
    rng = random.Random(cfg.seed)
    tgen = torch.Generator().manual_seed(cfg.seed)
    target = bits.to(device)
    history: list[dict[str, float]] = []
    steps = cfg.epochs * len(cameras)
    with Progress(steps, "embed", enabled=progress) as bar:
        for _ in range(cfg.epochs):
            order = list(range(len(cameras)))
            rng.shuffle(order)
            for v in order:
                current = Gaussians(means, log_scales, quats, logits, torch.cat([dc, rest], dim=1))
                render = rasterize(current, cameras[v], background=bg, validate=False).image
                attacked = None
                if cfg.model_attacks > 0 and rng.random() < cfg.model_attacks:
                    attacked = rasterize(_perturbed(current, rng, tgen, cfg.model_noise), cameras[v],
                                         background=bg, validate=False).image
                if attacks is not None and rng.random() < cfg.attacks:
                    base = render if attacked is None else attacked
                    attacked = _sample_attack(rng, attacks, base.clamp(0, 1), tgen)
                loss, terms, out_logits = loss_fn(render, originals[v], target, attacked)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                mask.step(opt)  # positions, when trained, are not masked (paper)
                acc = float(((out_logits > 0).float() == target).float().mean())
                terms.update(loss=float(loss.detach()), bit_acc=acc)
                history.append(terms)
                bar.update(loss=f"{terms['loss']:.4f}", bits=f"{acc:.3f}",
                           psnr=f"{float(psnr(render.detach(), originals[v])):.1f}")
    timings["finetune"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    result = Gaussians(means.detach(), log_scales.detach(), quats.detach(), logits.detach(),
                       torch.cat([dc, rest], dim=1).detach())
    accs, psnrs = [], []
    with torch.no_grad():
        for cam, orig in zip(cameras, originals):
            img = rasterize(result, cam, background=bg).image
            accs.append(float(((dec.decode_image(img.clamp(0, 1).unsqueeze(0))[0] > 0).float() == target).float().mean()))
            psnrs.append(float(psnr(img.clamp(0, 1), orig.clamp(0, 1))))
    timings["evaluate"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - start
    return EmbedResult(result, bits, message_to_hex(bits) if num_bits % 4 == 0 else "", prune, split,
                       timings, accs, psnrs, history)


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
def extract(images: ImageLike, *, num_bits: int = 32, decoder: torch.nn.Module | None = None) -> Extraction:
    """Reads the watermark bits from one or more images (e.g. screenshots of renders).

    Args:
        images: [3, H, W], [B, 3, H, W] or a list of [3, H, W] RGB images in [0, 1] (sizes may differ).
        num_bits: message length of the decoder.
        decoder: a custom decoder (LL2 subband -> logits); default: the shipped one for `num_bits`.

    Returns:
        An :class:`Extraction`.
    """
    from gsw.decoder.dwt import ll_subband

    imgs = _as_images(images)
    dec = _load_decoder(num_bits, decoder, imgs[0].device)
    logits = torch.cat([dec(ll_subband(img)) for img in imgs])
    return Extraction((logits > 0).float(), logits)


@dataclass
class Verdict:
    """Ownership test of images against a message.

    Attributes:
        bit_accuracy: per image, fraction of matching bits.
        matches: per image, number of matching bits.
        p_values: per image, P(an unmarked image matches at least as many bits) (binomial, p=1/2).
        p_value: combined over images (Fisher's method; assumes independent views, so it is
            optimistic for near-duplicate views).
    """

    bit_accuracy: list[float]
    matches: list[int]
    p_values: list[float]
    p_value: float

    def detected(self, fpr: float = DETECTION_FPR) -> bool:
        """Whether the combined p-value is at or below `fpr`."""
        return self.p_value <= fpr


@torch.no_grad()
def verify(source: ImageLike | tuple[Gaussians, Sequence[Camera]], message: MessageLike, *,
           num_bits: int | None = None, decoder: torch.nn.Module | None = None,
           background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Verdict:
    """Tests images (or renders of a model) for a given message.

    Args:
        source: images ([3,H,W], [B,3,H,W] or a list) or a `(gaussians, cameras)` pair to render.
        message: the claimed message (bits, hex or `"key:<secret>"`).
        num_bits: message length (inferred from bits/hex when omitted; required for keys).
        decoder: a custom decoder.
        background: render background for a model source.

    Returns:
        A :class:`Verdict`.
    """
    if num_bits is None:
        if isinstance(message, str) and not message.startswith("key:"):
            num_bits = 4 * len(message.lower().removeprefix("0x"))
        elif message is not None and not isinstance(message, str):
            num_bits = int(torch.as_tensor(message).numel())
        else:
            raise ValueError("num_bits is required for a key or a missing message")
    bits = as_message(message, num_bits)
    if isinstance(source, tuple) and len(source) == 2 and isinstance(source[0], Gaussians):
        g, cams = source
        images = [rasterize(g, cam, background=background).image for cam in cams]
    else:
        images = source
    ext = extract(images, num_bits=num_bits, decoder=decoder)
    matches = [int(v) for v in (ext.bits == bits.to(ext.bits)).sum(dim=1).tolist()]
    p_values = [binomial_p_value(m, num_bits) for m in matches]
    return Verdict([m / num_bits for m in matches], matches, p_values, fisher_combined_p_value(p_values))
