"""Recipients fine-tuned together on one device: a pool of K slots over stacked parameters.

Every recipient starts from the same FGD'd model (:class:`gsw.fingerprint.shared.WorkerScene`). The trained
parameters of K slots are stacked into ``[K, N, ...]`` tensors with per-slot Adam moments and step counts
and one update mask (:mod:`gsw.mark.mask`, computed once from the starting model). Per step every occupied
slot renders the next view of its own shuffled order (the order :func:`gsw.mark.embed.embed` draws from
``EmbedConfig.seed``), then ONE batched pass of the wavelet transform, decoder, LPIPS and loss over
``[B, 3, H, W]`` gives the sum of the per-recipient losses, so each recipient's update is that of
:func:`gsw.mark.embed.embed` with the same message and seed (up to float summation order).

A recipient leaves its slot when it is finished (:mod:`gsw.fingerprint.stopping`: early stopping on its own
training renders, or the step cap of ``EmbedConfig.epochs`` passes); its copy is scored, handed out, and the
slot is refilled with the next recipient (a fresh copy of the starting parameters, fresh Adam state). A copy
the rule redraws (:attr:`~gsw.fingerprint.stopping.EarlyStop.redraw`) is discarded and its recipient queued
first with its new message.
"""

from __future__ import annotations

import functools
import random
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import torch
from torch import Tensor
from torch.autograd.profiler import record_function

from gsw.camera import Camera
from gsw.fingerprint.stopping import EarlyStop, SlotMonitor
from gsw.gaussians import Gaussians
from gsw.mark.embed import (PARAMETER_GROUPS, EmbedConfig, apply_overrides, embedding_view_sampler, final_scores,
                            pick_view)
from gsw.mark.views import ViewSampler

__all__ = ["POOL_LPIPS", "References", "SlotParams", "CopyResult", "batched_loss", "check_pool_config",
           "finetune_batch", "pool_config"]

_BETAS, _EPS = (0.9, 0.999), 1e-15  # gsw.mark.embed's Adam (torch defaults, eps 1e-15)


#: The pool's LPIPS network: AlexNet, what its throughput and quality were measured with (BENCHMARKS.md, #26).
POOL_LPIPS = "alex"


def pool_config(**overrides) -> EmbedConfig:
    """The pool's default settings, plus ``overrides`` (:func:`gsw.mark.embed.apply_overrides`: a ``weights`` mapping
    replaces fields of the pool's weights): ``gsw embed``'s default recipe (:class:`EmbedConfig`: the SH rest frozen
    without a gradient mask, so that the mark lives where SH-degree-0 viewers and ``.splat`` / ``.spz`` exports keep it;
    the squared-error image term; no FGD) on the given cameras only (``novel_views=0``) with the AlexNet LPIPS term
    (:data:`POOL_LPIPS`). On lego 800x800 (one H200, 2026-11-29, BENCHMARKS.md "Twentieth GPU round") these copies read
    98-99 % of their bits after SH 0 / ``.splat``; with the SH rest trained under the paper's mask, 65 %.
    :func:`gsw.mark.embed.paper_config` with ``lpips_net=POOL_LPIPS`` is the paper's recipe (the pool's default until
    2026-11-29)."""
    return apply_overrides(EmbedConfig(lpips_net=POOL_LPIPS, novel_views=0.0), overrides)


def check_pool_config(cfg: EmbedConfig) -> None:
    """Refuses the :class:`EmbedConfig` settings the pool does not implement (rather than ignoring them).

    Raises:
        ValueError: render-size changes, train-time model attacks or a PSNR target.
    """
    unsupported = [name for name, on in (("render_scales", tuple(cfg.render_scales) != (1.0, 1.0)),
                                         ("model_attacks", cfg.model_attacks > 0),
                                         ("psnr_target", cfg.psnr_target is not None)) if on]
    if unsupported:
        raise ValueError(f"fingerprinting does not support EmbedConfig.{', '.join(unsupported)} (set by "
                         f"{'them' if len(unsupported) > 1 else 'it'}); use gsw.fingerprint.batched.pool_config() "
                         "as the base, or gsw embed per recipient for those settings")


def _stack(t: Tensor, k: int) -> Tensor:
    """``k`` stacked copies of ``t`` as a new leaf that requires grad: [k, *t.shape]."""
    return t.detach().unsqueeze(0).repeat(k, *([1] * t.dim())).contiguous().requires_grad_()


class SlotParams:
    """K slots' trainable parameters stacked along a leading axis, with per-slot Adam and the update mask.

    The update of slot ``j`` is, element-wise, ``torch.optim.Adam``'s (its own step count for the bias
    corrections) scaled by the mask: what :class:`gsw.mark.mask.UpdateMask` does to one recipient's Adam.

    Args:
        model: the shared starting model.
        k: number of slots.
        cfg: the embedding settings (learning rates, mask kind, frozen groups; positions stay shared while
            ``lr_position`` is 0).
    """

    def __init__(self, model: Gaussians, k: int, cfg: EmbedConfig) -> None:
        from gsw.mark.mask import exp_mask, stega_mask

        self.k, self.model = k, model.detach()
        stack = functools.partial(_stack, k=k)
        self.means = stack(model.means) if cfg.lr_position > 0 else self.model.means
        self.dc = stack(model.sh[:, :1])  # [K, N, 1, 3]
        self.rest = stack(model.sh[:, 1:])  # [K, N, C-1, 3]
        self.logits = stack(model.opacity_logits)  # [K, N]
        self.log_scales = stack(model.log_scales)  # [K, N, 3]
        self.quats = stack(model.quats)  # [K, N, 4]
        groups = []
        for name, p, lr in zip(PARAMETER_GROUPS, (self.dc, self.rest, self.logits, self.log_scales, self.quats),
                               (cfg.lr_f_dc, cfg.lr_f_rest, cfg.lr_opacity, cfg.lr_scaling, cfg.lr_rotation)):
            if name in cfg.freeze:
                p.requires_grad_(False)  # frozen: no gradient, no update
            else:
                groups.append((p, lr))
        maker = {"exp": exp_mask, "stega": stega_mask}.get(cfg.mask)
        if cfg.mask not in ("exp", "stega", "none"):
            raise ValueError(f"mask kind must be 'exp', 'stega' or 'none', got {cfg.mask!r}")
        # one recipient's mask (the stacked copies' masks are identical), broadcast over the slots
        self.groups = [(p, lr, None if maker is None else maker(p[0])) for p, lr in groups if p.numel() > 0]
        if cfg.lr_position > 0:
            self.groups.append((self.means, cfg.lr_position, None))  # positions are not masked (paper)
        self.exp_avg = [torch.zeros_like(p) for p, _, _ in self.groups]
        self.exp_avg_sq = [torch.zeros_like(p) for p, _, _ in self.groups]
        self.steps = [0] * k
        self._t = torch.zeros(k, dtype=torch.float64, device=self.dc.device)  # per-slot steps, on the device
        self._key: tuple[int, ...] | None = None
        self._on = torch.zeros(k, dtype=torch.bool, device=self.dc.device)

    def gaussians(self, j: int) -> Gaussians:
        """Slot ``j``'s current model (differentiable in its parameters)."""
        means = self.means[j] if self.means.dim() == 3 else self.means
        return Gaussians(means, self.log_scales[j], self.quats[j], self.logits[j],
                         torch.cat([self.dc[j], self.rest[j]], dim=1))

    def slot_models(self, slots: Sequence[int]) -> list[Gaussians]:
        """The current models of ``slots``, differentiable, through one ``unbind`` per parameter tensor (its
        backward stacks the slots' gradients once instead of one full-size gradient per indexed slot)."""
        dc, rest, logits, scales, quats = (t.unbind(0) for t in (self.dc, self.rest, self.logits, self.log_scales,
                                                                 self.quats))
        means = self.means.unbind(0) if self.means.dim() == 3 else None
        return [Gaussians(self.means if means is None else means[j], scales[j], quats[j], logits[j],
                          torch.cat([dc[j], rest[j]], dim=1)) for j in slots]

    @torch.no_grad()
    def reset(self, j: int) -> None:
        """Slot ``j`` starts over: the starting parameters, zero Adam moments, step 0."""
        sources = {id(self.dc): self.model.sh[:, :1], id(self.rest): self.model.sh[:, 1:],
                   id(self.logits): self.model.opacity_logits, id(self.log_scales): self.model.log_scales,
                   id(self.quats): self.model.quats, id(self.means): self.model.means}
        for (p, _, _), m, v in zip(self.groups, self.exp_avg, self.exp_avg_sq):
            p[j].copy_(sources[id(p)])
            m[j].zero_()
            v[j].zero_()
        self.steps[j] = 0
        self._t[j] = 0.0

    @torch.no_grad()
    def step(self, slots: Sequence[int]) -> None:
        """One masked Adam step of the ``slots`` (the others keep their parameters); clears the gradients.

        The per-slot step counts and bias corrections live on the device (no host-to-device copy per step).
        """
        for j in slots:
            self.steps[j] += 1
        if self._key != tuple(slots):
            self._key = tuple(slots)
            self._on = torch.zeros(self.k, dtype=torch.bool, device=self.dc.device)
            self._on[list(slots)] = True
        b1, b2 = _BETAS
        self._t += self._on
        inv_bc1 = torch.where(self._on, 1 / (1 - b1 ** self._t), 0.0).float()
        root2 = torch.where(self._on, (1 - b2 ** self._t).sqrt(), 1.0).float()
        for (p, lr, mask), m, v in zip(self.groups, self.exp_avg, self.exp_avg_sq):
            if p.grad is None:
                continue
            shape = (self.k,) + (1,) * (p.dim() - 1)
            size = (-lr * inv_bc1).view(shape)
            m.lerp_(p.grad, 1 - b1)
            v.mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
            scale = size if mask is None else size * mask
            p.addcdiv_(m * scale, (v.sqrt() / root2.view(shape)).add_(_EPS))
            p.grad = None


@dataclass
class References:
    """What the loss compares the renders of some views with, made once from those views' original renders.

    Attributes:
        highs: the wavelet detail subbands of the original renders (``gsw.decoder.dwt.dwt2(originals)[1]``: per
            level ``(LH, HL, HH)``, each [B, 3, h, w]).
        lpips: their LPIPS features (:meth:`gsw.metrics.lpips.LPIPS.references`, one [B, C, h, w] per tap), or
            None without an LPIPS term.
    """

    highs: list[tuple[Tensor, Tensor, Tensor]]
    lpips: list[Tensor] | None = None


def batched_loss(loss: torch.nn.Module, renders: Tensor, original: Tensor, messages: Tensor,
                 decoded: Tensor | None = None, message_weights: Tensor | None = None,
                 references: References | None = None) -> tuple[Tensor, Tensor]:
    """The sum over recipients of :class:`gsw.mark.loss.WatermarkLoss`, computed in one batched pass.

    Args:
        loss: the :class:`~gsw.mark.loss.WatermarkLoss` (its decoder, LPIPS network and weights are used).
        renders: [K, 3, H, W] the recipients' renders.
        original: [3, H, W] or [K, 3, H, W] the input model's render(s) of those views.
        messages: [K, k] the recipients' bits.
        decoded: optional [K, 3, H', W'] images to decode instead of ``renders`` (attacked copies).
        message_weights: optional [K] per-recipient message weights (default: the loss's weight).
        references: optional :class:`References` of ``original`` (batch K), when they are at hand
            (:meth:`gsw.fingerprint.shared.WorkerScene.references`): then one wavelet transform of the renders
            gives the decoder input and the subbands (compared with the references'), and LPIPS uses the
            references' features.

    Returns:
        (the summed loss, [K, k] decoder logits).
    """
    import torch.nn.functional as F

    from gsw.decoder.dwt import dwt2, ll_subband

    w = loss.weights
    target = original.expand_as(renders)
    diff = renders - target
    if references is None:
        logits = loss.decoder(ll_subband(renders if decoded is None else decoded))
        details = [band for level in dwt2(diff)[1] for band in level]  # the DWT is linear: the difference's
    else:  # one transform of the renders: their LL is the decoder input, their details minus the references'
        ll, highs = dwt2(renders)
        logits = loss.decoder(ll if decoded is None else ll_subband(decoded))
        details = [band - ref for level, refs in zip(highs, references.highs) for band, ref in zip(level, refs)]
    # per recipient: the terms of WatermarkLoss
    per = w.l1 * diff.abs().mean(dim=(1, 2, 3))
    if w.mse:  # opt-in: no extra pass over the K renders otherwise
        per = per + w.mse * diff.square().mean(dim=(1, 2, 3))
    per = per + w.subband * sum(d.abs().mean(dim=(1, 2, 3)) for d in details)
    bce = F.binary_cross_entropy_with_logits(logits * loss.logit_scale, messages.to(logits),
                                             reduction="none").mean(dim=1)
    per = per + (w.message * bce if message_weights is None else message_weights * bce)
    if loss.lpips is not None:
        per = per + w.lpips * (loss.lpips(renders, target) if references is None
                               else loss.lpips.distance(renders, references.lpips))
    return per.sum(), logits


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
        seconds: this recipient's share of the pool's wall time (its time in a slot / slots).
        steps: optimisation steps it took (more than the step cap when the rule extended it,
            :attr:`~gsw.fingerprint.stopping.EarlyStop.extend`).
        stopped_early: whether the stopping rule finished it before the step cap.
        message_weight: its message weight at the end (differs from the configured one under control).
        refusals: early stops refused by the confirmation before it finished.
        worker_setup_s: seconds its worker spent on the scene (models and original renders on the device, the
            loss) before its batch began: 0 when the worker had it cached from an earlier batch.
        worker_warm_s: seconds its worker's warm-up took (:func:`gsw.fingerprint.shared.warm_worker`: the
            original renders and the loss, made while the driver ran the set-up); 0 without one.
        redraws: new messages its recipient got (:attr:`~gsw.fingerprint.stopping.EarlyStop.redraw`); the steps,
            scores and seconds above are those of the last attempt.
        redrawn_steps: the steps of its discarded attempts.
        message: [k] the message this copy carries when it was redrawn (CPU), else None (the given one).
        probe_bit_accuracy: mean bit accuracy on the rule's probes (:attr:`~gsw.fingerprint.stopping.EarlyStop.probes`,
            viewpoints between the embedding views); None without them.
    """

    name: str
    gaussians: Gaussians
    bit_accuracy: float
    min_bit_accuracy: float
    psnr: float
    min_psnr: float
    seconds: float = 0.0
    steps: int = 0
    stopped_early: bool = False
    message_weight: float | None = None
    refusals: int = 0
    worker_setup_s: float = 0.0
    worker_warm_s: float = 0.0
    redraws: int = 0
    redrawn_steps: int = 0
    message: Tensor | None = None
    probe_bit_accuracy: float | None = None


def _attack_layers(cfg: EmbedConfig) -> dict | None:
    if cfg.attacks <= 0:
        return None
    from gsw.attacks.layers import matched_noise_layers, training_noise_layers

    layers = training_noise_layers() if cfg.attack_ranges == "training" else matched_noise_layers()
    return {k: v for k, v in layers.items() if k != "identity"}


@dataclass
class _Slot:
    """A recipient in a slot: its index in the job, its view order and attack random state, when it came in,
    with ``EmbedConfig.novel_views`` its own draws of sampled viewpoints (those of ``gsw.embed``'s ``_Views``), and
    with :attr:`EarlyStop.focus` the embedding views its last failed score read wrong (and their wrong-bit shares)."""

    index: int
    rng: random.Random
    tgen: torch.Generator
    order: list[int] = field(default_factory=list)
    start: float = 0.0
    view_rng: random.Random | None = None
    sampler: ViewSampler | None = None
    focus: list[int] = field(default_factory=list)
    focus_weights: list[float] = field(default_factory=list)
    focus_rng: random.Random | None = None

    def next_view(self, views: int) -> int:
        if not self.order:  # a new epoch: the shuffle of gsw.mark.embed
            self.order = list(range(views))
            self.rng.shuffle(self.order)
        return self.order.pop(0)


class _Pool:
    """The slots, their recipients and the step loop's pieces."""

    def __init__(self, scene, messages: Tensor, k: int, stop: EarlyStop | None, redrawable: Sequence[bool]) -> None:
        cfg: EmbedConfig = scene.shared.config
        self.scene, self.cfg = scene, cfg
        self.messages = messages.to(scene.device, torch.float32)
        self.redrawable = list(redrawable)
        self.redraws = [0] * len(self.redrawable)  # new messages per recipient
        self.redrawn_steps = [0] * len(self.redrawable)  # steps of its discarded attempts
        check_pool_config(cfg)  # a worker scene made without prepare_scene is checked too
        self.params = SlotParams(scene.model, k, cfg)
        self.monitor = SlotMonitor(k, cfg.weights.message, stop, scene.device)
        self.attacks = _attack_layers(cfg)
        self.slots: list[_Slot | None] = [None] * k
        self.cap = cfg.epochs * len(scene.shared.cameras)
        self.caps = [self.cap] * k  # per slot: the cap, or the cap of an extension
        # fresh sampled viewpoints (as gsw.embed's _Views); a bank's are the scene's
        self.sampler = None if cfg.view_bank else embedding_view_sampler(scene.bank.original, scene.shared.cameras, cfg)
        self._cache: dict = {}

    def fill(self, j: int, index: int) -> None:
        self.params.reset(j)
        self.monitor.reset(j)
        self.caps[j] = self.cap
        seed = self.cfg.seed
        self.slots[j] = _Slot(index, random.Random(seed), torch.Generator().manual_seed(seed),
                              start=time.perf_counter(), view_rng=random.Random(seed + 1),
                              sampler=None if self.sampler is None else self.sampler.reseeded(seed + 2),
                              focus_rng=random.Random(seed + 3))

    def refocus(self, j: int, views: Sequence[int], accuracies: Tensor) -> None:
        """Slot ``j``'s copy failed a confirmation with these [V] bit accuracies on ``views`` (scene view indices:
        the embedding views and the probes): with :attr:`EarlyStop.focus`, its later steps revisit the views it
        read wrong, weighted by their wrong bits."""
        rule = self.monitor.rule
        if rule is None or rule.focus <= 0:
            return
        wrong = [(v, w) for v, w in zip(views, (1 - accuracies).tolist()) if w > 0]
        slot = self.slots[j]
        slot.focus = [v for v, _ in wrong]
        slot.focus_weights = [w for _, w in wrong]

    def redraw(self, index: int, steps: int) -> None:
        """Recipient ``index`` gets its next message (:func:`gsw.mark.message.redrawn_message`) after an attempt
        of ``steps`` steps."""
        from gsw.mark.message import redrawn_message

        self.redraws[index] += 1
        self.redrawn_steps[index] += steps
        self.messages[index] = redrawn_message(self.messages[index], self.redraws[index]).to(self.messages)
        self._cache.clear()  # the cached message rows

    def counted(self, j: int) -> bool:
        """Whether slot ``j``'s steps count towards the progress total (recipients x cap): not a redraw's."""
        return self.redraws[self.slots[j].index] == 0

    def _indices(self, slots: tuple[int, ...]) -> tuple[Tensor, Tensor]:
        """The device index tensor of ``slots`` and their recipients' messages (cached while they stay)."""
        key = (slots, tuple(self.slots[j].index for j in slots))
        if key not in self._cache:
            self._cache.clear()
            dev = self.messages.device
            self._cache[key] = (torch.tensor(slots, device=dev),
                                self.messages[torch.tensor(list(key[1]), device=dev)])
        return self._cache[key]

    def active(self) -> list[int]:
        return [j for j, s in enumerate(self.slots) if s is not None]

    def _decoder_input(self, slot: _Slot, render: Tensor) -> Tensor:
        """What the message loss decodes for one slot (an attacked render with ``cfg.attacks``)."""
        if self.attacks is not None and slot.rng.random() < self.cfg.attacks:
            name = slot.rng.choice(sorted(self.attacks))
            return self.attacks[name](render.clamp(0, 1)[None], generator=slot.tgen)[0]
        return render

    def _view(self, slot: _Slot) -> tuple[Camera, int | Tensor, Tensor]:
        """A slot's camera at this step, its view for :meth:`WorkerScene.references` and the input model's render
        there: the next embedding view or, with ``cfg.novel_views``, as often a sampled viewpoint (as ``gsw.embed``
        draws them, from the recipient's own random state): one of the job's bank (``cfg.view_bank``) or a fresh
        one; with :attr:`EarlyStop.focus`, as often one of the views its last failed score read wrong."""
        scene = self.scene
        if slot.focus and slot.focus_rng.random() < self.monitor.rule.focus:
            v = slot.focus_rng.choices(slot.focus, slot.focus_weights)[0]
            return scene.camera(v), v, scene.original(v)
        v = slot.next_view(len(scene.shared.cameras))
        b = pick_view(slot.view_rng, self.cfg, len(scene.bank))
        if b == -1:
            cam = slot.sampler.sample()
            target = scene.bank.render_camera(cam)
            return cam, target, target
        if b is not None:
            v = len(scene.shared.cameras) + b
        return scene.camera(v), v, scene.original(v)

    def step(self) -> None:
        """One optimisation step of every occupied slot."""
        from gsw.render.rasterize import rasterize

        bg = self.cfg.background
        slots = self.active()
        cams, views, targets = zip(*(self._view(self.slots[j]) for j in slots))
        with record_function("gsw.pool.render"):  # labels for torch.profiler (benchmarks/fingerprint_throughput.py)
            renders = [rasterize(g, cam, background=bg, validate=False).image
                       for g, cam in zip(self.params.slot_models(slots), cams)]
            decoded = [self._decoder_input(self.slots[j], r) for j, r in zip(slots, renders)]
        # one batched pass per image size (attacked images may differ: one pass per slot)
        if self.attacks is None:
            sizes: dict[tuple[int, ...], list[int]] = {}
            for i, r in enumerate(renders):
                sizes.setdefault(tuple(r.shape), []).append(i)
            groups = list(sizes.values())
        else:
            groups = [[i] for i in range(len(slots))]
        total = 0.0
        with record_function("gsw.pool.loss"):
            for g in groups:
                r = torch.stack([renders[i] for i in g])
                t = torch.stack([targets[i] for i in g])
                d = None if self.attacks is None else torch.stack([decoded[i] for i in g])
                idx, msgs = self._indices(tuple(slots[i] for i in g))
                refs = self.scene.references([views[i] for i in g])
                part, logits = batched_loss(self.scene.loss, r, t, msgs, d, self.monitor.weights[idx], refs)
                self.monitor.observe(idx, logits, msgs, r, t)
                total = total + part
        with record_function("gsw.pool.backward"):
            total.backward()
        with record_function("gsw.pool.adam"):
            self.params.step(slots)


def finetune_batch(scene, names: Sequence[str], messages: Tensor, on_step: Callable[[int], None] | None = None, *,
                   slots: int | None = None, stop: EarlyStop | None = None,
                   on_copy: Callable[[CopyResult], None] | None = None,
                   redrawable: Sequence[bool] | None = None) -> list[CopyResult]:
    """Fine-tunes one copy per recipient in a pool of ``slots`` slots and scores them on the embedding views.

    Args:
        scene: a :class:`gsw.fingerprint.shared.WorkerScene`.
        names: the recipients.
        messages: [R, k] their bits.
        on_step: progress: called with the number of recipient-steps done (after every step; a recipient
            that stops early reports the steps it skipped when it leaves; steps of an extension beyond the cap
            are not counted, nor those of a redrawn recipient's later attempts, so the total is recipients x cap).
        slots: recipients fine-tuned together (default: all of them).
        stop: the early-stopping rule (default: none; every recipient runs ``EmbedConfig.epochs`` passes).
        on_copy: called with each copy as soon as it is finished (in finishing order).
        redrawable: per recipient, whether ``stop`` may give it a new message (default: none; only messages gsw
            drew, never given or key-derived ones).

    Returns:
        One :class:`CopyResult` per recipient, in input order.
    """
    k = min(len(names), slots or len(names))
    pool = _Pool(scene, messages, k, stop, redrawable or [False] * len(names))
    queue = list(range(len(names)))
    for j in range(k):
        pool.fill(j, queue.pop(0))
    results: dict[int, CopyResult] = {}
    every, tick = (stop.check_every if stop is not None else 1), 0
    while pool.active():
        pool.step()
        tick += 1
        steps = pool.params.steps
        if on_step is not None:
            on_step(sum(steps[j] <= pool.cap and pool.counted(j) for j in pool.active()))
        if tick % every and not any(steps[j] >= pool.caps[j] for j in pool.active()):
            continue
        occupied = [s is not None for s in pool.slots]
        for j in pool.monitor.decide(list(steps), occupied, pool.caps):
            result = _finish(pool, j, names, k)
            if result is None:  # its copy failed the confirmation on the embedding views: go on
                continue
            if result is _REDRAWN:  # discarded: the recipient starts over first, with its new message
                queue.insert(0, pool.slots[j].index)
            else:
                if on_step is not None and pool.cap > result[1].steps and pool.counted(j):
                    on_step(pool.cap - result[1].steps)
                results[result[0]] = result[1]
                if on_copy is not None:
                    on_copy(result[1])
            pool.slots[j] = None
            if queue:
                pool.fill(j, queue.pop(0))
    return [results[i] for i in range(len(names))]


_REDRAWN = object()  # _finish: the copy was discarded for a new message


def _finish(pool: _Pool, j: int, names: Sequence[str], k: int) -> tuple[int, CopyResult] | object | None:
    """Slot ``j``'s copy, scored on the embedding views; None when the score fails the rule's confirmation and
    the recipient goes on: before the step cap (:meth:`~gsw.fingerprint.stopping.SlotMonitor.refuse`), or at
    the cap with :attr:`~gsw.fingerprint.stopping.EarlyStop.extend` not yet used (its cap moves up once);
    :data:`_REDRAWN` when, at its last cap, the rule discards it for a new message (:meth:`_Pool.redraw`)."""
    slot = pool.slots[j]
    steps = pool.params.steps[j]
    with torch.no_grad():
        copy = pool.params.gaussians(j).detach().clone()
    scene, message, rule = pool.scene, pool.messages[slot.index], pool.monitor.rule
    views = list(range(len(scene.shared.cameras)))
    accs, psnrs = _score(scene, copy, message, views)
    acc, acc_min, ps, ps_min = float(accs.mean()), float(accs.min()), float(psnrs.mean()), float(psnrs.min())
    probe_acc = None
    if rule is not None and rule.probes:
        probes = scene.probe_views(rule.probes)
        probe_accs = _score(scene, copy, message, probes)[0]
        probe_acc = float(probe_accs.mean())
        views, accs = views + probes, torch.cat([accs, probe_accs])
    if rule is not None and not rule.confirmed(acc, ps, probe_acc):
        if steps < pool.caps[j]:  # an early stop (before the cap or the extension's cap)
            pool.monitor.refuse(j)
            pool.refocus(j, views, accs)
            return None
        if pool.caps[j] == pool.cap and rule.extension(pool.cap):
            pool.caps[j] = pool.cap + rule.extension(pool.cap)
            pool.refocus(j, views, accs)
            return None
    if rule is not None and steps >= pool.caps[j] and pool.redrawable[slot.index] and rule.redraws(
            acc, pool.redraws[slot.index], probe_acc):
        pool.redraw(slot.index, steps)
        return _REDRAWN
    weight = float(pool.monitor.weights[j])
    redraws = pool.redraws[slot.index]
    return slot.index, CopyResult(names[slot.index], copy.to("cpu"), acc, acc_min, ps, ps_min,
                                  (time.perf_counter() - slot.start) / k, steps, steps < pool.cap, weight,
                                  pool.monitor.rejections[j], redraws=redraws,
                                  redrawn_steps=pool.redrawn_steps[slot.index],
                                  message=pool.messages[slot.index].cpu() if redraws else None,
                                  probe_bit_accuracy=probe_acc)


def _score(scene, copy: Gaussians, target: Tensor, views: Sequence[int]) -> tuple[Tensor, Tensor]:
    """[V] bit accuracies and [V] PSNRs (dB) of one copy on the scene's ``views`` (CPU)."""
    acc, ps = final_scores(copy, [scene.camera(v) for v in views], [scene.original(v) for v in views],
                           scene.loss.decoder, target, scene.shared.config.background)
    return acc.cpu(), ps.cpu()
