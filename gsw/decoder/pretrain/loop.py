"""The host-side pre-training loop of one encoder/decoder pair (HiDDeN under noise layers).

:func:`train` trains an encoder + decoder on random crops (and flips) of photos kept on the host. The
encoder's residual is rescaled per image to a fixed PSNR (ramped from ``psnr_start`` to ``psnr_target``), so
the networks learn *where* to put the watermark, not how strong to make it. Each batch is split into one chunk
per noise layer; the decoder reads the LL2 subband (:func:`gsw.decoder.dwt.ll_subband`) of each attacked
chunk; the loss is the mean BCE-with-logits over chunks. Attack strengths ramp up over ``noise_ramp`` of the
run. Time- or step-budgeted, checkpointed, resumable; logs bit accuracy per noise layer.

It crops in Python and runs real JPEG on the CPU, too slow to converge in minutes on a GPU: the shipped
decoders come from :func:`gsw.decoder.pretrain.multi.train_multi`. The schedule helpers here are shared.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from gsw.attacks.layers import NoiseLayer, training_noise_layers
from gsw.decoder.dwt import ll_subband
from gsw.decoder.hidden import HiddenDecoder, HiddenEncoder, bit_accuracy
from gsw.decoder.pretrain.config import TrainConfig
from gsw.decoder.pretrain.data import random_crops
from gsw.decoder.pretrain.encoders import embed
from gsw.decoder.whitening import WhiteningLayer
from gsw.decoder.zoo import atomic_torch_save

__all__ = ["chunks", "lr_factor", "ramp", "train"]


def ramp(progress: float, frac: float) -> float:
    """0 -> 1 linearly over the first ``frac`` of the run (1 throughout when ``frac`` <= 0)."""
    return 1.0 if frac <= 0 else min(1.0, progress / frac)


def lr_factor(progress: float, warmup: float) -> float:
    """Learning-rate factor at ``progress`` in [0,1]: linear warmup, then cosine down to 0.02."""
    if progress < warmup:
        return max(progress / warmup, 1e-3)
    return 0.5 * (1 + math.cos(math.pi * min(1.0, (progress - warmup) / max(1e-9, 1 - warmup)))) * 0.98 + 0.02


def chunks(n: int, k: int) -> list[slice]:
    """``k`` contiguous slices of nearly equal length covering ``range(n)``."""
    bounds = np.linspace(0, n, k + 1).round().astype(int)
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def _layers(cfg: TrainConfig) -> dict[str, NoiseLayer]:
    """The training noise layers ``cfg`` selects, by name."""
    layers = training_noise_layers(cfg.jpeg_mode)
    if cfg.noise_layers is not None:
        layers = {n: layers[n] for n in cfg.noise_layers}
    return layers


def _decode_chunks(
    decoder: torch.nn.Module,
    whiten: WhiteningLayer | None,
    x_w: torch.Tensor,
    msgs: torch.Tensor,
    layers: dict[str, NoiseLayer],
    gen: torch.Generator,
    amp: bool,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Mean BCE over the chunks of ``x_w`` [B,3,H,W], chunk i attacked by layer i; bit accuracy per layer."""
    losses, accs = [], {}
    dev_type = x_w.device.type
    for (name, layer), sl in zip(layers.items(), chunks(x_w.shape[0], len(layers))):
        y = layer(x_w[sl], generator=gen)
        ll = ll_subband(y)
        with torch.autocast(dev_type, dtype=torch.bfloat16, enabled=amp):
            logits = decoder(ll)
        logits = logits.float()
        if whiten is not None:
            logits = whiten(logits)
        losses.append(F.binary_cross_entropy_with_logits(logits, msgs[sl]))
        accs[name] = bit_accuracy(logits.detach(), msgs[sl]).mean()
    vals = torch.stack(list(accs.values())).tolist()  # one device sync per step
    return torch.stack(losses).mean(), dict(zip(accs, vals))


class _HostTrainer:
    """State of one :func:`train` run: networks, optimizer, checkpoint, log window and clocks."""

    def __init__(self, cfg: TrainConfig, device: torch.device, ckpt_path: str | Path | None, verbose: bool) -> None:
        self.cfg, self.device, self.verbose = cfg, device, verbose
        torch.manual_seed(cfg.seed)
        self.enc = HiddenEncoder(cfg.num_bits, cfg.enc_blocks, cfg.channels).to(device)
        self.dec = HiddenDecoder(cfg.num_bits, cfg.dec_blocks, cfg.channels).to(device)
        self.params = list(self.enc.parameters()) + list(self.dec.parameters())
        self.opt = torch.optim.AdamW(self.params, lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.layers = _layers(cfg)
        self.state: dict[str, Any] = {"config": dataclasses.asdict(cfg), "step": 0, "elapsed": 0.0, "log": [],
                                      "val": []}
        self.ckpt_path = Path(ckpt_path) if ckpt_path else None
        if self.ckpt_path is not None and self.ckpt_path.exists():
            prev = torch.load(self.ckpt_path, map_location=device, weights_only=False)
            self.enc.load_state_dict(prev["encoder"])
            self.dec.load_state_dict(prev["decoder"])
            self.opt.load_state_dict(prev["optimizer"])
            self.state.update({k: prev[k] for k in ("step", "elapsed", "log", "val")})
            self._print(f"resumed at step {self.state['step']} ({self.state['elapsed']:.0f} s)")
        self.gen = torch.Generator().manual_seed(cfg.seed * 1000 + self.state["step"])
        self.enc.train()
        self.dec.train()
        self.window: dict[str, list[float]] = {n: [] for n in [*self.layers, "loss"]}
        self.t_last = self.t_ckpt = self.t_val = time.perf_counter()

    def _print(self, msg: str) -> None:
        """``msg`` on stdout with the bit length, when verbose."""
        if self.verbose:
            print(f"[k={self.cfg.num_bits}] {msg}", flush=True)

    def progress(self) -> float:
        """Fraction of the budget (steps, or seconds of training) done."""
        if self.cfg.time_budget_s is not None:
            return min(1.0, self.state["elapsed"] / self.cfg.time_budget_s)
        return min(1.0, self.state["step"] / max(1, self.cfg.steps))

    def save(self) -> None:
        """Write the checkpoint (atomically), when there is one."""
        if self.ckpt_path is not None:
            self.state.update(encoder=self.enc.state_dict(), decoder=self.dec.state_dict(),
                              optimizer=self.opt.state_dict())
            atomic_torch_save(self.state, self.ckpt_path)

    def step(self, images: list[torch.Tensor]) -> tuple[float, float]:
        """One optimizer step on a batch of crops of ``images``; returns (PSNR, attack strength) used."""
        cfg, p = self.cfg, self.progress()
        for g in self.opt.param_groups:
            g["lr"] = cfg.lr * lr_factor(p, cfg.warmup)
        strength = ramp(p, cfg.noise_ramp)
        for layer in self.layers.values():
            layer.strength = strength
        psnr = cfg.psnr_start + (cfg.psnr_target - cfg.psnr_start) * ramp(p, cfg.psnr_ramp)
        imgs = random_crops(images, cfg.batch_size, cfg.crop, self.gen, self.device)
        msgs = torch.randint(0, 2, (cfg.batch_size, cfg.num_bits), generator=self.gen).float().to(self.device)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=cfg.amp):
            x_w = embed(self.enc, imgs, msgs, psnr)
        loss, accs = _decode_chunks(self.dec, None, x_w, msgs, self.layers, self.gen, cfg.amp)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.params, 1.0)
        self.opt.step()
        self.state["step"] += 1
        for n, a in accs.items():
            self.window[n].append(a)
        self.window["loss"].append(loss.item())
        now = time.perf_counter()
        self.state["elapsed"] += now - self.t_last
        self.t_last = now
        return psnr, strength

    def log(self, psnr: float, strength: float) -> None:
        """Append the window's mean accuracies and loss to the log and start a new window."""
        entry = {"step": self.state["step"], "elapsed": round(self.state["elapsed"], 1),
                 "lr": self.opt.param_groups[0]["lr"], "psnr": psnr, "strength": strength}
        entry.update({f"acc_{n}" if n != "loss" else n: float(np.mean(v)) for n, v in self.window.items()})
        self.state["log"].append(entry)
        self.window = {n: [] for n in self.window}
        self._print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in entry.items()}))

    def validate(self, val_fn: Callable[..., dict[str, Any]], psnr: float) -> None:
        """Run ``val_fn(encoder, decoder, psnr)`` in eval mode; its time does not count as training time."""
        self.enc.eval(), self.dec.eval()
        v = val_fn(self.enc, self.dec, psnr)
        self.enc.train(), self.dec.train()
        v.update(step=self.state["step"], elapsed=round(self.state["elapsed"], 1))
        self.state["val"].append(v)
        self._print(f"val {json.dumps(v)}")
        self.t_val = self.t_last = time.perf_counter()

    def checkpoint(self) -> None:
        """Save; the time it takes is not training time."""
        self.save()
        self.t_ckpt = self.t_last = time.perf_counter()

    def finish(self) -> dict[str, Any]:
        """Eval mode, a last checkpoint, and the state :func:`train` returns."""
        self.enc.eval()
        self.dec.eval()
        self.save()
        self.state.update(encoder=self.enc.state_dict(), decoder=self.dec.state_dict(),
                          optimizer=self.opt.state_dict())
        self.state["modules"] = (self.enc, self.dec)
        return self.state


def train(
    cfg: TrainConfig,
    train_images: list[torch.Tensor],
    device: torch.device | str = "cpu",
    ckpt_path: str | Path | None = None,
    val_fn: Callable[..., dict[str, Any]] | None = None,
    val_every_s: float = 120.0,
    verbose: bool = True,
) -> dict[str, Any]:
    """Pre-train an encoder + decoder on crops of ``train_images`` (uint8 [3,H,W]); resumes from ``ckpt_path``
    if it exists and checkpoints there every ``cfg.ckpt_every_s`` (atomically).

    Args:
        val_fn: ``(encoder, decoder, psnr) -> dict`` called in eval mode every ``val_every_s``.

    Returns:
        a state dict ``{"config", "step", "elapsed", "encoder", "decoder", "optimizer", "log", "val"}`` (also
        what the checkpoint holds) plus ``"modules": (encoder, decoder)`` in eval mode.
    """
    run = _HostTrainer(cfg, torch.device(device), ckpt_path, verbose)
    while run.progress() < 1.0:
        psnr, strength = run.step(train_images)
        now = run.t_last
        if run.state["step"] % cfg.log_every == 0:
            run.log(psnr, strength)
        if val_fn is not None and now - run.t_val > val_every_s:
            run.validate(val_fn, psnr)
        if now - run.t_ckpt > cfg.ckpt_every_s:
            run.checkpoint()
    return run.finish()
