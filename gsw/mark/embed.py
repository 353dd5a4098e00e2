"""`gsw.embed`: the 3D-GSW watermark into a trained 3DGS model (reading it: :mod:`gsw.mark.detect`).

Pipeline of :func:`embed`: render the original model from every training view (the targets), optionally
FGD phase 1 (prune) and phase 2 (split) (``EmbedConfig.fgd``: the paper's recipe; off by default), then
fine-tune the SH colours, opacities, scales and rotations (positions frozen by default) with Adam, one
shuffled view per step, against :class:`~gsw.mark.loss.WatermarkLoss`, with the gradient mask applied to the updates
(:mod:`gsw.mark.mask`). Optional train-time attack sampling decodes an attacked copy of the
render (noise, crop, JPEG, blur, rotation, scaling) to harden the watermark; train-time model distortions
(:mod:`gsw.attacks.distort`: parameter noise, SH degree 0, straight-through ``.splat`` / ``.spz`` / 8-bit
exports) decode the render of a distorted copy. The targets are renders of the original model, so steps may
use viewpoints beyond the given cameras (:mod:`gsw.mark.views`: jittered, interpolated and orbit poses,
varied focal length and render size; the fidelity losses apply there too), and a model without cameras is
embedded from views sampled around its content.
"""

from __future__ import annotations

import dataclasses
import math
import random
import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.gaussians import Gaussians
from gsw.mark.detect import load_decoder_for
from gsw.mark.fgd import (PRUNE_THRESHOLD, TOP_PERCENT, PruneReport, SplitReport, check_opacity_rule, fgd_prune,
                          fgd_split)
from gsw.mark.loss import PAPER_IMAGE_TERM, LossWeights, WatermarkLoss, WeightControl
from gsw.mark.mask import UpdateMask
from gsw.mark.message import MessageLike, as_message, message_to_hex
from gsw.mark.views import ViewSampler, ViewSamplerConfig, scale_camera
from gsw.metrics.image import psnr
from gsw.progress import Progress
from gsw.render.rasterize import rasterize

__all__ = ["EmbedConfig", "EmbedResult", "EmbedSetup", "PAPER_RECIPE", "PARAMETER_GROUPS", "apply_overrides",
           "check_config", "check_freeze", "embed",
           "ViewBank", "embedding_view_sampler", "paper_config", "pick_view", "prepare_embedding"]

#: Fine-tuned parameter groups of :func:`embed` (:attr:`EmbedConfig.freeze` names; positions: ``lr_position``).
PARAMETER_GROUPS: tuple[str, ...] = ("f_dc", "f_rest", "opacity", "scaling", "rotation")


@dataclass
class EmbedConfig:
    """Settings of :func:`embed`.

    Defaults: the grid method ``freeze-rest+views`` (BENCHMARKS.md §9d-9e) without FGD (§9j): the view-dependent
    SH colours (``f_rest``) stay fixed and the others are updated without the exponential mask, so the mark lives
    where SH-degree-0 viewers and ``.splat`` / ``.spz`` exports keep it, and every step renders a fresh viewpoint
    sampled around the content, so the mark reaches viewpoints no camera saw; learning rates of the official
    code except the SH colours (f_dc x2, f_rest x8, measured best with the shipped decoders, §6). The paper's
    recipe (FGD, given cameras only, exponential mask, every group trained): :func:`paper_config`.

    Attributes:
        epochs: passes over the shuffled training views.
        lr_f_dc, lr_f_rest, lr_opacity, lr_scaling, lr_rotation, lr_position: Adam learning rates
            (position 0 = frozen, as in the paper).
        freeze: parameter groups kept at their (post-FGD) values, names of :data:`PARAMETER_GROUPS`
            (``f_dc``, ``f_rest``, ``opacity``, ``scaling``, ``rotation``); e.g. ``("f_rest",)`` keeps the
            view-dependent SH untouched, so the mark lives where SH-degree-0 viewers and ``.splat`` keep it.
        weights: loss weights (default :class:`LossWeights`: the squared-error image term; the paper's recipe pins
            its L1 term, :data:`PAPER_RECIPE`).
        logit_scale: factor on the decoder logits inside the message BCE (the official code: 10).
        lpips_net: "vgg", "alex" or None (no LPIPS term; set weights.lpips = 0).
        mask: "exp" (3D-GSW), "stega" (StegaNeRF-style) or "none".
        fgd: run FGD (prune + split) before fine-tuning (off by default: its split changes the renders of a
            trained model before the fine-tune begins and adds ~28 % Gaussians; without it, at equal bits, 1.1 dB
            more on the built-in scene, the same PSNR with this default recipe on lego 800x800 and 0.6-0.7 dB more
            with the paper's recipe or a PSNR target there, 0.2 dB less on a 200x200 lego model, BENCHMARKS.md
            §7a, §9j, §9k; the paper's recipe keeps it).
        prune_threshold: FGD phase-1 threshold on the normalised contribution (:func:`gsw.mark.fgd.fgd_prune`).
        top_percent: FGD phase-2 share of patches (percent).
        split_quantile: FGD phase-2 low-contribution quantile that is split.
        split_opacity: the split children's opacity rule, ``"coincident"`` or ``"footprint"``
            (:func:`gsw.mark.fgd.split_gaussians`; BENCHMARKS.md §9j).
        attacks: train-time attack sampling: probability of decoding an attacked render.
        model_attacks: train-time model-attack sampling: probability of decoding the render of a perturbed
            copy of the model instead (Gaussian noise of std ``model_noise`` on every raw parameter but
            the positions, or the SH reduced to degree 0, each half of the time); fidelity losses stay on
            the unperturbed render.  Combines with ``attacks`` (the image attack then hits that render).
        model_noise: std of that parameter noise.
        model_attack_kinds: the train-time model distortions drawn (uniformly) at those steps, names of
            :data:`gsw.attacks.distort.DISTORTIONS` (``noise``, ``sh0``, ``splat``, ``spz``, ``8bit``).
        attack_ranges: ranges of the image attacks: ``"training"`` (the decoder pre-training's,
            :func:`gsw.attacks.layers.training_noise_layers`) or ``"matched"`` (up to the evaluation's
            strengths, :func:`gsw.attacks.layers.matched_noise_layers`).
        novel_views: share of the steps rendered from a sampled viewpoint (:class:`gsw.mark.views.ViewSampler`
            around the content) instead of a given camera; its target is the original model's render there.
        view_bank: 0: every such step samples a fresh viewpoint; ``B > 0``: ``B`` viewpoints are sampled once
            (:class:`ViewBank`, seeded) and each such step picks one of them, whose original render
            (and, in the fingerprint pool, loss references) is made once instead of per step.
        render_scales: ``(smallest, largest)`` render-size factor (log-uniform) of every step's camera, at most
            ``max_render_side`` pixels per side (a random window of larger renders, :func:`gsw.mark.views.scale_camera`);
            ``(1, 1)``: the cameras' own size.
        max_render_side: largest rendered side during fine-tuning, pixels.
        sampled_views: without cameras, how many sampled views stand in for them (FGD, epochs, final scores).
        sampled_view_size: without cameras, the image side of those views, pixels.
        psnr_target: hold the fine-tune's running PSNR (its renders against the original renders, dB) at this
            target by steering the message weight (:class:`gsw.mark.loss.WeightControl`: raised while the
            PSNR is above the target, lowered while below, within ``psnr_weight_range`` times the configured
            weight); None: a fixed weight.
        psnr_weight_range: how far the steered weight may move from ``weights.message`` (factor, >= 1).
        background: render background.
        seed: RNG seed (view order, attacks, sampled views); never the message (a missing message is drawn
            secretly).
    """

    epochs: int = 8
    lr_f_dc: float = 5e-3  # official code: 2.5e-3
    lr_f_rest: float = 1e-3  # official code: 1.25e-4
    lr_opacity: float = 0.05
    lr_scaling: float = 5e-3
    lr_rotation: float = 1e-3
    lr_position: float = 0.0
    freeze: tuple[str, ...] = ("f_rest",)
    weights: LossWeights = field(default_factory=LossWeights)
    logit_scale: float = 1.0
    lpips_net: str | None = "vgg"
    mask: str = "none"
    fgd: bool = False
    prune_threshold: float = PRUNE_THRESHOLD
    top_percent: float = TOP_PERCENT
    split_quantile: float = 0.5
    split_opacity: str = "coincident"
    attacks: float = 0.0
    model_attacks: float = 0.0
    model_noise: float = 0.1
    model_attack_kinds: tuple[str, ...] = ("noise", "sh0")
    attack_ranges: str = "training"
    novel_views: float = 1.0
    view_bank: int = 0
    render_scales: tuple[float, float] = (1.0, 1.0)
    max_render_side: int = 1024
    sampled_views: int = 48
    sampled_view_size: int = 512
    psnr_target: float | None = None
    psnr_weight_range: float = 4.0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0


#: The paper's recipe as :class:`EmbedConfig` overrides (``"weights"`` overrides single fields of
#: :class:`LossWeights`): FGD, given cameras only, the exponential gradient mask, every parameter group trained, no
#: train-time attacks, a fixed message weight, the L1 image term (:data:`gsw.mark.loss.PAPER_IMAGE_TERM`).
PAPER_RECIPE: dict = {"fgd": True, "freeze": (), "mask": "exp", "novel_views": 0.0, "render_scales": (1.0, 1.0),
                      "attacks": 0.0, "model_attacks": 0.0, "psnr_target": None, "weights": dict(PAPER_IMAGE_TERM)}


def apply_overrides(config: EmbedConfig, overrides: Mapping[str, Any]) -> EmbedConfig:
    """A copy of ``config`` with ``overrides`` applied.

    Args:
        config: the base configuration (not modified).
        overrides: EmbedConfig field -> value; ``"weights"`` is a :class:`LossWeights` (replacing the weights) or a
            mapping of LossWeights fields to values (replacing those fields of ``config.weights``).

    Returns:
        A new :class:`EmbedConfig`.

    Raises:
        ValueError: an unknown field.
    """
    known = {f.name for f in dataclasses.fields(EmbedConfig)}
    unknown = set(overrides) - known
    if unknown:
        raise ValueError(f"unknown EmbedConfig fields {sorted(unknown)}; choose from {sorted(known)}")
    values = {k: v for k, v in overrides.items() if k != "weights"}
    if "background" in values:
        values["background"] = tuple(values["background"])
    weights = overrides.get("weights")
    if isinstance(weights, LossWeights):
        values["weights"] = weights
    elif weights is not None:
        loss_fields = {f.name for f in dataclasses.fields(LossWeights)}
        if set(weights) - loss_fields:
            raise ValueError(f"unknown LossWeights fields {sorted(set(weights) - loss_fields)}; choose from "
                             f"{sorted(loss_fields)}")
        values["weights"] = dataclasses.replace(config.weights, **weights)
    return dataclasses.replace(config, **values)


def paper_config(**overrides) -> EmbedConfig:
    """The paper's recipe (:data:`PAPER_RECIPE` on the defaults), with further ``overrides`` (field -> value; a
    :class:`LossWeights` for ``weights`` replaces the recipe's weights, a mapping replaces single fields)."""
    return apply_overrides(apply_overrides(EmbedConfig(), PAPER_RECIPE), overrides)


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
        cameras: the views embedded from (the given cameras, or the sampled ones standing in for them).
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
    cameras: list[Camera] = field(default_factory=list)


def _sample_attack(gen: random.Random, attacks: dict, render: Tensor, tgen: torch.Generator) -> Tensor:
    name = gen.choice(sorted(attacks))
    return attacks[name](render.unsqueeze(0), generator=tgen)[0]



@dataclass
class EmbedSetup:
    """The per-scene work of :func:`embed`, the same for every message embedded into one model
    (:func:`prepare_embedding`; :mod:`gsw.fingerprint` does it once for many recipients).

    Attributes:
        model: the model after FGD (detached; the input model itself when FGD is off), on the input device.
        originals: per camera, the [3, H, W] render of the input model (the fidelity targets).
        decoder: the frozen decoder on the input device.
        prune, split: FGD reports (None when FGD is off).
        timings: seconds of "renders" and "fgd".
    """

    model: Gaussians
    originals: list[Tensor]
    decoder: torch.nn.Module
    prune: PruneReport | None
    split: SplitReport | None
    timings: dict[str, float]


def prepare_embedding(gaussians: Gaussians, cameras: Sequence[Camera], *, num_bits: int = 32,
                      images: Sequence[Tensor] | None = None, config: EmbedConfig | None = None,
                      decoder: torch.nn.Module | None = None) -> EmbedSetup:
    """Checks the inputs, renders the original views, runs FGD and sets up the decoder: everything of
    :func:`embed` that does not depend on the message.

    Args:
        gaussians: the trained model (not modified).
        cameras: its training views.
        num_bits: message length (selects the shipped decoder).
        images: optional [3, H, W] training images, used by FGD phase 1's error weighting.
        config: :class:`EmbedConfig` (background, FGD settings).
        decoder: a custom frozen decoder (LL2 subband -> logits); default: the shipped one.

    Returns:
        An :class:`EmbedSetup`.

    Raises:
        ValueError: no cameras, a bad config, non-finite parameters or a decoder of another length.
    """
    cfg = config or EmbedConfig()
    check_config(cfg, cameras)
    gaussians.check_finite()
    dec = load_decoder_for(num_bits, decoder, gaussians.device)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    with torch.no_grad():
        originals = [rasterize(gaussians, cam, background=cfg.background).image for cam in cameras]
    timings["renders"] = time.perf_counter() - start

    t0 = time.perf_counter()
    model, prune, split = gaussians.detach().clone(), None, None
    if cfg.fgd:
        model, prune = fgd_prune(model, cameras, images, threshold=cfg.prune_threshold, background=cfg.background)
        model, split = fgd_split(model, cameras, top_percent=cfg.top_percent, low_quantile=cfg.split_quantile,
                                 background=cfg.background, opacity_rule=cfg.split_opacity)
    timings["fgd"] = time.perf_counter() - t0
    return EmbedSetup(model, originals, dec, prune, split, timings)


def embed(gaussians: Gaussians, cameras: Sequence[Camera] | None = None, *, message: MessageLike = None,
          num_bits: int = 32, images: Sequence[Tensor] | None = None,
          config: EmbedConfig | None = None, decoder: torch.nn.Module | None = None,
          progress: bool = True) -> EmbedResult:
    """Embeds an N-bit message into every rendered view of a 3DGS model.

    Args:
        gaussians: the trained model (not modified).
        cameras: its training views; None: ``config.sampled_views`` views sampled around the model's content
            (:class:`gsw.mark.views.ViewSampler`, ``config.sampled_view_size`` pixels; returned in
            :attr:`EmbedResult.cameras`).
        message: None (a fresh secret message from the OS entropy pool, never from ``config.seed``: read it
            from the result's ``message`` / ``message_hex`` and keep it, or record it with
            :func:`gsw.registry.record_mark`), bits, a hex string or `"key:<secret>"` (see
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
    if cameras is None:
        cameras = _stand_in_views(gaussians, cfg)
    bits = as_message(message, num_bits)  # None: secret (os.urandom); the seed drives the optimisation only
    start = time.perf_counter()
    setup = prepare_embedding(gaussians, cameras, num_bits=num_bits, images=images, config=cfg, decoder=decoder)
    model, originals, dec, prune, split = setup.model, setup.originals, setup.decoder, setup.prune, setup.split
    device = gaussians.device
    timings: dict[str, float] = dict(setup.timings)

    t0 = time.perf_counter()
    params = _Trainable(model, cfg)
    loss_fn = WatermarkLoss(dec, cfg.weights, cfg.lpips_net, cfg.logit_scale).to(device)
    history = _finetune(params, _Views(gaussians, cameras, originals, cfg), loss_fn, bits.to(device), cfg, progress)
    timings["finetune"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    result = params.gaussians().detach()
    accs, psnrs = (v.tolist() for v in final_scores(result, cameras, originals, dec, bits.to(device),
                                                     cfg.background))
    timings["evaluate"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - start
    return EmbedResult(result, bits, message_to_hex(bits) if num_bits % 4 == 0 else "", prune, split,
                       timings, accs, psnrs, history, list(cameras))


def _stand_in_views(gaussians: Gaussians, cfg: EmbedConfig) -> list[Camera]:
    """Views sampled around a model's content (orbit poses at one size) for a model without cameras."""
    if cfg.sampled_views < 1:
        raise ValueError(f"EmbedConfig.sampled_views must be >= 1, got {cfg.sampled_views}")
    sampler_cfg = ViewSamplerConfig(size_range=(1.0, 1.0), base_size=cfg.sampled_view_size,
                                    elevation_deg=(-85.0, 85.0))
    cams = ViewSampler(gaussians, None, sampler_cfg, seed=cfg.seed).sample_many(cfg.sampled_views)
    return [dataclasses.replace(c, name=f"sampled_{i:03d}") for i, c in enumerate(cams)]


def check_config(cfg: EmbedConfig, cameras: Sequence[Camera]) -> None:
    """Refuses settings no fine-tune can run (before anything is computed or written).

    Args:
        cfg: the settings.
        cameras: the embedding views.

    Raises:
        ValueError: no cameras, probabilities outside [0, 1], a negative model noise or bad view settings.
    """
    if len(cameras) == 0:
        raise ValueError("embed needs at least one camera")
    lo, hi = cfg.render_scales
    if not 0 < lo <= hi:
        raise ValueError(f"EmbedConfig.render_scales must satisfy 0 < low <= high, got {cfg.render_scales}")
    if cfg.attack_ranges not in ("training", "matched"):
        raise ValueError(f"EmbedConfig.attack_ranges must be 'training' or 'matched', got {cfg.attack_ranges!r}")
    check_opacity_rule(cfg.split_opacity, "EmbedConfig.split_opacity")
    from gsw.attacks.distort import DISTORTIONS

    if not cfg.model_attack_kinds or set(cfg.model_attack_kinds) - set(DISTORTIONS):
        raise ValueError(f"EmbedConfig.model_attack_kinds must be names of {DISTORTIONS}, got "
                         f"{cfg.model_attack_kinds}")
    for name in ("attacks", "model_attacks", "novel_views"):
        if not 0.0 <= getattr(cfg, name) <= 1.0:
            raise ValueError(f"EmbedConfig.{name} is a probability in [0, 1], got {getattr(cfg, name)}")
    if cfg.model_noise < 0:
        raise ValueError(f"EmbedConfig.model_noise must be >= 0, got {cfg.model_noise}")
    if isinstance(cfg.view_bank, bool) or not isinstance(cfg.view_bank, int) or cfg.view_bank < 0:
        raise ValueError(f"EmbedConfig.view_bank must be an integer >= 0, got {cfg.view_bank!r}")
    if cfg.psnr_target is not None and not (math.isfinite(cfg.psnr_target) and cfg.psnr_target > 0):
        raise ValueError(f"EmbedConfig.psnr_target must be a positive PSNR in dB or None, got {cfg.psnr_target}")
    if not cfg.psnr_weight_range >= 1:
        raise ValueError(f"EmbedConfig.psnr_weight_range must be >= 1, got {cfg.psnr_weight_range}")
    check_freeze(cfg.freeze, cfg.lr_position)


def check_freeze(groups: Sequence[str], lr_position: float = 0.0) -> None:
    """Refuses an :attr:`EmbedConfig.freeze` that names an unknown group, or every group while the positions are
    frozen too (``lr_position <= 0``: nothing would be trained).

    Raises:
        ValueError: naming the groups.
    """
    unknown = set(groups) - set(PARAMETER_GROUPS)
    if unknown or set(groups) == set(PARAMETER_GROUPS) and lr_position <= 0:
        raise ValueError(f"EmbedConfig.freeze must name some (not all) of {PARAMETER_GROUPS}, got {tuple(groups)}")


class _Trainable:
    """The fine-tuned parameters (positions trained only with ``lr_position > 0``, the groups of
    ``cfg.freeze`` not at all), Adam and the update mask."""

    def __init__(self, model: Gaussians, cfg: EmbedConfig) -> None:
        train = {name: name not in cfg.freeze for name in PARAMETER_GROUPS}
        self.means = model.means.clone().requires_grad_(cfg.lr_position > 0)
        self.dc = model.sh[:, :1].clone().requires_grad_(train["f_dc"])
        self.rest = model.sh[:, 1:].clone().requires_grad_(train["f_rest"])
        self.logits = model.opacity_logits.clone().requires_grad_(train["opacity"])
        self.log_scales = model.log_scales.clone().requires_grad_(train["scaling"])
        self.quats = model.quats.clone().requires_grad_(train["rotation"])
        groups = [(p, lr) for p, lr in ((self.dc, cfg.lr_f_dc), (self.rest, cfg.lr_f_rest),
                                        (self.logits, cfg.lr_opacity), (self.log_scales, cfg.lr_scaling),
                                        (self.quats, cfg.lr_rotation)) if p.requires_grad]
        if cfg.lr_position > 0:
            groups.append((self.means, cfg.lr_position))
        trainable = [p for p, _ in groups if p.numel() > 0]
        self.opt = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in groups if p.numel() > 0], eps=1e-15)
        # positions, when trained, are not masked (paper)
        self.mask = UpdateMask([p for p in trainable if p is not self.means], kind=cfg.mask)

    def gaussians(self) -> Gaussians:
        """The current model (differentiable in the trained parameters)."""
        return Gaussians(self.means, self.log_scales, self.quats, self.logits, torch.cat([self.dc, self.rest], dim=1))


def embedding_view_sampler(original: Gaussians, cameras: Sequence[Camera], cfg: EmbedConfig) -> ViewSampler | None:
    """The sampler of a fine-tune's extra viewpoints (``cfg.novel_views``; None without): around ``original``'s
    content, at the given cameras' image sizes (at most ``cfg.max_render_side``), seeded from ``cfg.seed``."""
    if cfg.novel_views <= 0:
        return None
    return ViewSampler(original, cameras, ViewSamplerConfig(size_range=(1.0, 1.0), max_side=cfg.max_render_side),
                       seed=cfg.seed + 2)


class ViewBank:
    """The ``cfg.view_bank`` viewpoints sampled once for a fine-tune's sampled steps (none without
    ``cfg.novel_views`` or a bank: the first draws of :func:`embedding_view_sampler`), and the input model's render
    of each, made on first use and kept.

    Args:
        original: the input model (its renders are the targets; on the fine-tune's device).
        cameras: the given cameras (the sampler's sizes and poses).
        cfg: the settings (``novel_views``, ``view_bank``, ``seed``, ``background``).

    Attributes:
        cameras: the bank's viewpoints.
        original: the input model.
    """

    def __init__(self, original: Gaussians, cameras: Sequence[Camera], cfg: EmbedConfig) -> None:
        sampler = embedding_view_sampler(original, cameras, cfg)
        self.cameras: list[Camera] = [] if sampler is None else sampler.sample_many(cfg.view_bank)
        self.original, self._background = original, cfg.background
        self._renders: dict[int, Tensor] = {}

    def __len__(self) -> int:
        return len(self.cameras)

    def render(self, b: int) -> Tensor:
        """[3, H, W] the input model's render of bank viewpoint ``b`` (made once)."""
        if b not in self._renders:
            self._renders[b] = self.render_camera(self.cameras[b])
        return self._renders[b]

    @torch.no_grad()
    def render_camera(self, camera: Camera) -> Tensor:
        """[3, H, W] the input model's render from any ``camera`` (a freshly sampled viewpoint's target)."""
        return rasterize(self.original, camera, background=self._background, validate=False).image


def pick_view(rng: random.Random, cfg: EmbedConfig, bank_size: int) -> int | None:
    """Which viewpoint a fine-tune step renders instead of its given camera, drawn from ``rng`` (the order of
    draws is part of the seed's meaning): None for the given camera; else an index into the view bank, or -1
    for a fresh sample (no bank)."""
    if cfg.novel_views <= 0 or rng.random() >= cfg.novel_views:
        return None
    return rng.randrange(bank_size) if bank_size else -1


class _Views:
    """Each step's camera and target: a given camera (its cached original render) or, with
    ``cfg.novel_views``, a sampled viewpoint (a fresh one, or one of ``cfg.view_bank`` drawn once with its render
    kept); rescaled by ``cfg.render_scales`` (a fresh original render)."""

    def __init__(self, original: Gaussians, cameras: Sequence[Camera], originals: Sequence[Tensor],
                 cfg: EmbedConfig) -> None:
        self.cameras, self.originals, self.cfg = list(cameras), list(originals), cfg
        self.rng = random.Random(cfg.seed + 1)
        self.sampler = embedding_view_sampler(original, cameras, cfg)
        self.bank = ViewBank(original, cameras, cfg)

    def __len__(self) -> int:
        return len(self.cameras)

    def step(self, v: int) -> tuple[Camera, Tensor]:
        """The camera and the original model's render for the step that would use given view ``v``."""
        cam, target = self.cameras[v], self.originals[v]
        b = pick_view(self.rng, self.cfg, len(self.bank))
        if b == -1:
            cam, target = self.sampler.sample(), None
        elif b is not None:
            cam, target = self.bank.cameras[b], self.bank.render(b)
        lo, hi = self.cfg.render_scales
        if (lo, hi) != (1.0, 1.0):
            scale = math.exp(self.rng.uniform(math.log(lo), math.log(hi)))
            cam, target = scale_camera(cam, scale, self.cfg.max_render_side, self.rng), None
        if target is None:
            target = self.bank.render_camera(cam)
        return cam, target


def _decoder_input(current: Gaussians, cam: Camera, render: Tensor, cfg: EmbedConfig, attacks: dict | None,
                   rng: random.Random, tgen: torch.Generator) -> Tensor | None:
    """What the message loss decodes at this step: None (the render), or the render of a distorted model
    and / or an attacked image."""
    from gsw.attacks.distort import distort

    attacked = None
    if cfg.model_attacks > 0 and rng.random() < cfg.model_attacks:
        _, distorted = distort(current, cfg.model_attack_kinds, rng, tgen, cfg.model_noise)
        attacked = rasterize(distorted, cam, background=cfg.background, validate=False).image
    if attacks is not None and rng.random() < cfg.attacks:
        base = render if attacked is None else attacked
        attacked = _sample_attack(rng, attacks, base.clamp(0, 1), tgen)
    return attacked


def _finetune(params: _Trainable, views: _Views, loss_fn: WatermarkLoss, target: Tensor, cfg: EmbedConfig,
              progress: bool) -> list[dict[str, float]]:
    """Adam over shuffled views against the watermark loss; returns the per-step loss terms and bit accuracy."""
    attacks = None
    if cfg.attacks > 0:
        from gsw.attacks.layers import matched_noise_layers, training_noise_layers

        layers = training_noise_layers() if cfg.attack_ranges == "training" else matched_noise_layers()
        attacks = {k: v for k, v in layers.items() if k != "identity"}
    rng = random.Random(cfg.seed)
    tgen = torch.Generator().manual_seed(cfg.seed)
    control = None if cfg.psnr_target is None else WeightControl(cfg.weights.message, cfg.psnr_target,
                                                                  max_factor=cfg.psnr_weight_range)
    weight = cfg.weights.message
    history: list[dict[str, float]] = []
    with Progress(cfg.epochs * len(views), "embed", enabled=progress) as bar:
        for _ in range(cfg.epochs):
            order = list(range(len(views)))
            rng.shuffle(order)
            for v in order:
                cam, original = views.step(v)
                current = params.gaussians()
                render = rasterize(current, cam, background=cfg.background, validate=False).image
                attacked = _decoder_input(current, cam, render, cfg, attacks, rng, tgen)
                loss, terms, out_logits = loss_fn(render, original, target, attacked, message_weight=weight)
                params.opt.zero_grad(set_to_none=True)
                loss.backward()
                params.mask.step(params.opt)
                acc = float(((out_logits > 0).float() == target).float().mean())
                step_psnr = float(psnr(render.detach().clamp(0, 1), original.clamp(0, 1)))
                terms.update(loss=float(loss.detach()), bit_acc=acc, psnr=step_psnr, message_weight=weight)
                if control is not None:
                    weight = control.observe(step_psnr)
                history.append(terms)
                bar.update(loss=f"{terms['loss']:.4f}", bits=f"{acc:.3f}", psnr=f"{step_psnr:.1f}")
    return history


#: Views decoded together when a model is scored on its views (same-size views only).
SCORE_CHUNK = 16


@torch.no_grad()
def final_scores(result: Gaussians, cameras: Sequence[Camera], originals: Sequence[Tensor],
                 dec: torch.nn.Module, target: Tensor, bg: tuple[float, float, float]) -> tuple[Tensor, Tensor]:
    """Per view, the bit accuracy decoded from the render of ``result`` and its PSNR against the original.

    Args:
        result: the watermarked model.
        cameras: the views; ``originals`` their [3, H, W] renders of the input model.
        dec: the decoder (LL subbands -> logits).
        target: [k] the message.
        bg: background colour.

    Returns:
        ([V] bit accuracies, [V] PSNRs in dB), on the model's device; views of one size are decoded
        :data:`SCORE_CHUNK` at a time.
    """
    from gsw.decoder.dwt import ll_subband

    images = [rasterize(result, cam, background=bg, validate=False).image.clamp(0, 1) for cam in cameras]
    psnrs = torch.stack([psnr(img, orig.clamp(0, 1)) for img, orig in zip(images, originals)])
    step = SCORE_CHUNK if len({tuple(im.shape) for im in images}) == 1 else 1
    logits = torch.cat([dec(ll_subband(torch.stack(images[i:i + step]))) for i in range(0, len(images), step)])
    return ((logits > 0).float() == target).float().mean(dim=1), psnrs
