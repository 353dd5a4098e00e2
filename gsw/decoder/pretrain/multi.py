"""The device-resident pre-training loop that produced the shipped decoders: every bit length at once.

The host-side loop (:mod:`gsw.decoder.pretrain.loop`) crops in Python and runs real JPEG on the CPU, too slow
to converge in a few minutes on a GPU. :func:`train_multi` instead

* keeps the training photos on the device as one uint8 tensor and takes a batch of random crops (+ flips)
  with one batched gather (:func:`~gsw.decoder.pretrain.data.image_bank`,
  :func:`~gsw.decoder.pretrain.data.bank_crops`);
* trains several bit lengths at once: one encoder/decoder pair per bit length, all fed the same image
  batch, one backward and one (fused on CUDA) AdamW step for all of them;
* attacks with device-only noise layers (:class:`~gsw.attacks.layers.GpuAttacks`, the ranges of
  :func:`gsw.attacks.layers.training_noise_layers`, kornia's differentiable JPEG), random parameters from
  device generators (per image) or a host ``random.Random`` (per batch), so a step never waits for the device;
* follows a curriculum: first ``clean_frac`` of the run without attacks at a strong watermark
  (``psnr_start``), then the attack strength ramps to 1 and the PSNR to ``psnr_target``;
* optionally (``MultiConfig.balance``) also trains the decoder to be unbiased on unmarked crops of several
  sizes (:func:`balance_loss`), which whitening alone cannot give: the raw outputs of unmarked images shift
  with the image size, so a median fitted at one size leaves bits biased at another.

The same loop fine-tunes encoders alone against frozen, whitened decoders (``finetune_encoders=True``).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F

from gsw.attacks.layers import GpuAttacks
from gsw.decoder.dwt import ll_subband
from gsw.decoder.hidden import HiddenDecoder, HiddenEncoder, bit_accuracy
from gsw.decoder.pretrain.config import MultiConfig
from gsw.decoder.pretrain.data import bank_crops
from gsw.decoder.pretrain.encoders import embed_scaled, make_encoder
from gsw.decoder.pretrain.loop import chunks, lr_factor
from gsw.decoder.whitening import WhiteningLayer

__all__ = ["StepHook", "balance_loss", "describe_entry", "schedule", "train_multi"]

#: ``on_step(fraction_done, log_entry_or_None)``: called after every step of :func:`train_multi`.
StepHook = Callable[[float, "dict[str, Any] | None"], None]


def schedule(cfg: MultiConfig, p: float) -> tuple[float, float, float]:
    """(learning-rate factor, attack strength, PSNR) of the joint training at progress ``p`` in [0,1]."""
    lr = lr_factor(p, cfg.warmup)
    span = lambda end: min(1.0, max(0.0, (p - cfg.clean_frac) / max(1e-9, end - cfg.clean_frac)))  # noqa: E731
    strength = span(cfg.noise_ramp_end) if p >= cfg.clean_frac else 0.0
    psnr = cfg.psnr_start + (cfg.psnr_target - cfg.psnr_start) * (span(cfg.psnr_ramp_end) if p >= cfg.clean_frac else 0.0)
    return lr, strength, psnr


def balance_loss(logits: torch.Tensor) -> torch.Tensor:
    """Unmarked-balance loss: mean over bits of (batch mean of tanh(logit))^2, for logits [B,k] of
    *unmarked* images.  Zero when every bit is 1 on half of the batch (tanh is a soft sign), so it pushes
    each bit's P(1) over unmarked images towards 0.5 without asking for any particular code."""
    return torch.tanh(logits.float()).mean(0).pow(2).mean()


def _train_mode(decoder: HiddenDecoder, freeze_bn: bool) -> None:
    """Decoder in training mode; with ``freeze_bn`` its BatchNorm layers stay in eval mode, so the network
    trained is exactly the one used at inference (running statistics no longer follow the batches)."""
    decoder.train()
    if freeze_bn:
        for mod in decoder.modules():
            if isinstance(mod, torch.nn.modules.batchnorm._BatchNorm):
                mod.eval()


def _decoder_input(images: torch.Tensor, channels_last: bool) -> torch.Tensor:
    """LL2 subband (float32) of images [B,3,H,W], in the decoder's memory format."""
    ll = ll_subband(images.float())
    return ll.contiguous(memory_format=torch.channels_last) if channels_last else ll


def _to_cl(m: torch.nn.Module, on: bool) -> torch.nn.Module:
    """``m`` with its convolutions in channels-last memory format when ``on``."""
    if on:
        for mod in m.modules():  # only the convolutions (a TemplateEncoder's templates are 5-D)
            if isinstance(mod, torch.nn.Conv2d):
                mod.to(memory_format=torch.channels_last)
    return m


class _MultiRun:
    """State of one :func:`train_multi` run: networks, optimizer, generators, accuracy sums, log, clocks."""

    def __init__(self, cfg: MultiConfig, bank: torch.Tensor, encoders: list[torch.nn.Module] | None,
                 decoders: list[HiddenDecoder] | None, whitenings: list[WhiteningLayer] | None,
                 finetune: bool) -> None:
        dev = self.dev = bank.device
        self.cfg, self.bank, self.finetune = cfg, bank, finetune
        torch.manual_seed(cfg.seed)
        if encoders is None:
            encoders = [make_encoder(k, cfg) for k in cfg.bits]
        if decoders is None:
            decoders = [HiddenDecoder(k, cfg.dec_blocks, cfg.channels, cfg.dec_norm) for k in cfg.bits]
        self.encoders = [_to_cl(e.to(dev), cfg.channels_last) for e in encoders]
        self.decoders = [_to_cl(d.to(dev), cfg.channels_last) for d in decoders]
        self.whitenings: list[WhiteningLayer] | None = None
        if finetune:
            if whitenings is None:
                raise ValueError("finetune_encoders=True needs the decoders' whitenings")
            self.whitenings = [w.to(dev) for w in whitenings]
            for d in self.decoders:
                d.eval().requires_grad_(False)
            params = [p for e in self.encoders for p in e.parameters()]
        else:
            for d in self.decoders:
                _train_mode(d, cfg.freeze_bn)
            params = [p for m in (*self.encoders, *self.decoders) for p in m.parameters()]
        for e in self.encoders:
            e.train()
        self.opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay,
                                     **({"fused": True} if dev.type == "cuda" else {}))
        self.gen = torch.Generator(device=dev).manual_seed(cfg.seed * 7919 + (1 if finetune else 0))
        self.attacks = GpuAttacks(dev, cfg.seed + (101 if finetune else 0))
        self.names = list(cfg.noise_layers)
        self.acc_sum = torch.zeros(len(cfg.bits), len(self.names), device=dev)
        self.cnt = [0] * len(self.names)
        self.loss_sum = torch.zeros((), device=dev)
        self.bal_sum = torch.zeros(len(cfg.bits), device=dev)
        self.n_loss = 0
        self.log: list[dict[str, Any]] = []
        self.vals: list[dict[str, Any]] = []
        self.step, self.elapsed = 0, 0.0
        self.t_last = self.t_val = self.t_start = time.perf_counter()
        self.chunks = chunks(cfg.batch_size, max(1, cfg.noise_chunks))
        self.balance_on = cfg.balance > 0 and not finetune

    def progress(self) -> float:
        """Fraction of the budget (steps, or seconds of training) done."""
        if self.cfg.time_budget_s is not None:
            return min(1.0, self.elapsed / self.cfg.time_budget_s)
        return min(1.0, self.step / max(1, self.cfg.steps))

    def _picks(self, strength: float) -> list[int]:
        """The noise layer (index into ``names``) of each chunk of this step's batch."""
        names = self.names
        if strength <= 0.0:
            return [names.index("identity") if "identity" in names else 0] * len(self.chunks)
        picks = [self.attacks.rng.randrange(len(names)) for _ in self.chunks]
        if self.cfg.clean_chunk and "identity" in names:
            picks[0] = names.index("identity")
        return picks

    def _balance_term(self, m: int, strength: float, cover_size: int) -> torch.Tensor:
        """Balance loss of decoder ``m`` on unmarked crops of side ``cover_size``, decoded as at inference
        (eval-mode BatchNorm: in train mode the batch statistics would hide exactly the shift that biases
        the bits)."""
        cfg = self.cfg
        cover = bank_crops(self.bank, cfg.balance_batch, cover_size, self.gen, cfg.channels_last)
        cover = self.attacks.view(cover, strength) if cfg.view_warp else cover
        ll = _decoder_input(cover, cfg.channels_last)
        self.decoders[m].eval()
        with torch.autocast(self.dev.type, dtype=torch.bfloat16, enabled=cfg.amp):
            u = self.decoders[m](ll)
        _train_mode(self.decoders[m], cfg.freeze_bn)
        bal = balance_loss(u)
        self.bal_sum[m] += bal.detach()
        return cfg.balance * bal

    def _add_pair_loss(self, total: torch.Tensor | float, m: int, imgs: torch.Tensor, picks: list[int],
                       psnr: float, strength: float, cover_size: int) -> torch.Tensor:
        """``total`` plus the loss of pair ``m`` on this step's crops ``imgs`` [B,3,crop,crop] (+ its balance
        term)."""
        cfg, B = self.cfg, self.cfg.batch_size
        msgs = torch.randint(0, 2, (B, cfg.bits[m]), device=self.dev, generator=self.gen).float()
        with torch.autocast(self.dev.type, dtype=torch.bfloat16, enabled=cfg.amp):
            x_w = embed_scaled(self.encoders[m], imgs, msgs, psnr, cfg.enc_down)
        for sl, li in zip(self.chunks, picks):
            y = self.attacks.view(x_w[sl], strength) if cfg.view_warp else x_w[sl]
            ll = _decoder_input(self.attacks.apply(self.names[li], y, strength), cfg.channels_last)
            with torch.autocast(self.dev.type, dtype=torch.bfloat16, enabled=cfg.amp):
                logits = self.decoders[m](ll)
            logits = logits.float()
            if self.whitenings is not None:
                logits = self.whitenings[m](logits)
            total = total + F.binary_cross_entropy_with_logits(logits, msgs[sl]) * ((sl.stop - sl.start) / B)
            self.acc_sum[m, li] += bit_accuracy(logits.detach(), msgs[sl]).mean()
        if self.balance_on:
            total = total + self._balance_term(m, strength, cover_size)
        return total  # type: ignore[return-value]

    def train_step(self) -> tuple[float, float, float]:
        """One optimizer step for every pair; returns (lr factor, PSNR, attack strength) used."""
        cfg, p = self.cfg, self.progress()
        if self.finetune:
            lrf, strength, psnr = 0.5 * (1 + math.cos(math.pi * p)), 1.0, cfg.psnr_target
        else:
            lrf, strength, psnr = schedule(cfg, p)
        for g in self.opt.param_groups:
            g["lr"] = cfg.lr * lrf
        imgs = bank_crops(self.bank, cfg.batch_size, cfg.crop, self.gen, cfg.channels_last)
        picks = self._picks(strength)
        cover_size = (min(self.attacks.rng.choice(cfg.balance_sizes), *self.bank.shape[-2:])
                      if self.balance_on else 0)
        total: torch.Tensor | float = 0.0
        for m in range(len(cfg.bits)):
            total = self._add_pair_loss(total, m, imgs, picks, psnr, strength, cover_size)
        for li in picks:
            self.cnt[li] += 1
        self.opt.zero_grad(set_to_none=True)
        total.backward()  # type: ignore[union-attr]
        if not self.finetune:
            for e, d in zip(self.encoders, self.decoders):
                torch.nn.utils.clip_grad_norm_(list(e.parameters()) + list(d.parameters()), 1.0, foreach=True)
        self.opt.step()
        self.loss_sum += total.detach() / len(cfg.bits)  # type: ignore[union-attr]
        self.n_loss += 1
        self.step += 1
        self._tick()
        return lrf, psnr, strength

    def _tick(self) -> None:
        """Count the time since the last tick as training time."""
        now = time.perf_counter()
        self.elapsed += now - self.t_last
        self.t_last = now

    def log_entry(self, lrf: float, psnr: float, strength: float) -> dict[str, Any]:
        """Mean accuracies per bit length and noise layer since the last entry (one device sync)."""
        cfg, names = self.cfg, self.names
        accs = (self.acc_sum / torch.tensor([max(1, c) for c in self.cnt], device=self.dev)).tolist()  # sync
        self._tick()
        entry: dict[str, Any] = {"step": self.step, "elapsed": round(self.elapsed, 1), "lr": cfg.lr * lrf,
                                 "psnr": round(psnr, 2), "strength": round(strength, 3),
                                 "loss": float(self.loss_sum) / max(1, self.n_loss)}
        for m, k in enumerate(cfg.bits):
            entry[f"k{k}"] = {names[li]: round(accs[m][li], 4) for li in range(len(names)) if self.cnt[li]}
        if self.balance_on:
            entry["balance"] = {f"k{k}": round(float(self.bal_sum[m]) / max(1, self.n_loss), 5)
                                for m, k in enumerate(cfg.bits)}
        self.log.append(entry)
        self.acc_sum.zero_()
        self.bal_sum.zero_()
        self.loss_sum.zero_()
        self.cnt, self.n_loss = [0] * len(names), 0
        return entry

    def train_mode(self) -> None:
        """Back to training mode after a validation (decoders stay frozen in a fine-tune)."""
        for e in self.encoders:
            e.train()
        if not self.finetune:
            for d in self.decoders:
                _train_mode(d, self.cfg.freeze_bn)

    def validate(self, val_fn: Callable[..., dict[str, Any]], psnr: float) -> dict[str, Any]:
        """``val_fn(encoders, decoders, psnr)`` in eval mode; its time does not count as training time."""
        for mod in (*self.encoders, *self.decoders):
            mod.eval()
        v = val_fn(self.encoders, self.decoders, psnr)
        self.train_mode()
        v.update(step=self.step, elapsed=round(self.elapsed, 1))
        self.vals.append(v)
        self.t_val = self.t_last = time.perf_counter()
        return v

    def finish(self) -> dict[str, Any]:
        """Networks in eval mode (decoders trainable again after a fine-tune) and the run's summary."""
        if self.dev.type == "cuda":
            torch.cuda.synchronize()
        for mod in (*self.encoders, *self.decoders):
            mod.eval()
        if self.finetune:
            for d in self.decoders:
                d.requires_grad_(True)
        return {"encoders": self.encoders, "decoders": self.decoders, "step": self.step, "elapsed": self.elapsed,
                "log": self.log, "val": self.vals, "steps_per_s": self.step / max(self.elapsed, 1e-9),
                "wall_s": time.perf_counter() - self.t_start}


def describe_entry(entry: dict[str, Any], bits: tuple[int, ...], tag: str, elapsed: float, psnr: float,
           strength: float) -> str:
    """The one-line report of a :func:`train_multi` log entry (accuracies per bit length and noise layer)."""
    accs = " ".join(f"k{k}:" + "/".join(f"{v:.3f}" for v in entry[f"k{k}"].values()) for k in bits)
    return (f"[{tag}step {entry['step']} {elapsed:.0f}s {entry['step'] / max(elapsed, 1e-9):.2f} it/s psnr "
            f"{psnr:.1f} str {strength:.2f} loss {entry['loss']:.4f}] {accs}")


def train_multi(
    cfg: MultiConfig,
    bank: torch.Tensor,
    *,
    encoders: list[HiddenEncoder] | list[torch.nn.Module] | None = None,
    decoders: list[HiddenDecoder] | None = None,
    whitenings: list[WhiteningLayer] | None = None,
    finetune_encoders: bool = False,
    val_fn: Callable[..., dict[str, Any]] | None = None,
    val_every_s: float = 60.0,
    verbose: bool = True,
    tag: str = "",
    on_step: StepHook | None = None,
) -> dict[str, Any]:
    """Train one encoder/decoder pair per bit length in ``cfg.bits`` on crops of ``bank`` (uint8 [N,3,H,W]
    from :func:`~gsw.decoder.pretrain.data.image_bank`, on the training device).

    With ``finetune_encoders=True`` (pass trained ``encoders``, ``decoders`` and ``whitenings``) only the
    encoders are trained, against the frozen eval-mode decoders followed by their whitening, at
    ``psnr_target`` and full attack strength from the start (the situation of the 3DGS embedding).

    Args:
        val_fn: ``(encoders, decoders, psnr) -> dict`` called in eval mode every ``val_every_s``.
        verbose: print a line per log entry (every ``cfg.log_every`` steps) and per validation.
        tag: prefix of those lines.
        on_step: called after every step with the fraction of the budget done and the new log entry (or None).

    Returns:
        ``{"encoders", "decoders", "step", "elapsed", "log", "val", "steps_per_s", "wall_s"}``.
    """
    run = _MultiRun(cfg, bank, encoders, decoders, whitenings, finetune_encoders)
    while run.progress() < 1.0:
        lrf, psnr, strength = run.train_step()
        entry = None
        if run.step % cfg.log_every == 0 or run.progress() >= 1.0:
            entry = run.log_entry(lrf, psnr, strength)
            if verbose:
                print(describe_entry(entry, cfg.bits, tag, run.elapsed, psnr, strength), flush=True)
        if val_fn is not None and time.perf_counter() - run.t_val > val_every_s:
            v = run.validate(val_fn, psnr)
            if verbose:
                print(f"[{tag}val] {json.dumps(v)}", flush=True)
        if on_step is not None:
            on_step(run.progress(), entry)
    return run.finish()
