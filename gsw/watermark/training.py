"""HiDDeN pre-training of the watermark decoder (with its encoder) under noise layers.

The pipeline (``benchmarks/train_decoder.py`` is the command-line entry point):

1. :func:`train` - encoder + decoder on random crops (and flips) of photos. The encoder's residual is
   rescaled per image to a fixed PSNR (ramped from ``psnr_start`` to ``psnr_target``), so the networks
   learn *where* to put the watermark, not how strong to make it. Each batch is split into one chunk per
   noise layer; the decoder reads the LL2 subband (:func:`gsw.watermark.dwt.ll_subband`) of each attacked
   chunk; the loss is the mean BCE-with-logits over chunks. Attack strengths ramp up over ``noise_ramp``
   of the run. Time- or step-budgeted, checkpointed, resumable; logs bit accuracy per noise layer.
2. :func:`fit_decoder_whitening` - PCA whitening of the frozen decoder on unmarked training photos.
3. :func:`finetune_encoder` - optional: a short encoder-only fine-tune against the frozen whitened
   decoder (the situation of the 3DGS embedding), so the shipped decoder is shown to carry messages.

Only this subpackage is imported (no compiled extension), so it runs wherever torch does.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from .dwt import ll_subband
from .hidden import HiddenDecoder, HiddenEncoder, bit_accuracy
from .noise import NoiseLayer, clamp_st, training_noise_layers
from .whitening import WhiteningLayer

__all__ = [
    "TrainConfig",
    "load_images",
    "random_crops",
    "embed",
    "train",
    "fit_decoder_whitening",
    "finetune_encoder",
]


@dataclasses.dataclass
class TrainConfig:
    num_bits: int = 32
    channels: int = 64  # network width (64 for the shipped decoders; smaller only for tests)
    enc_blocks: int = 4
    dec_blocks: int = 8
    crop: int = 128  # training crop side (LL2 is crop/4)
    batch_size: int = 128  # split evenly over the noise layers
    lr: float = 1e-3
    weight_decay: float = 0.0
    psnr_start: float = 24.0  # PSNR of the watermarked crops at the start ...
    psnr_target: float = 30.0  # ... and after psnr_ramp of the run
    psnr_ramp: float = 0.4
    noise_ramp: float = 0.3  # attack strength ramps 0 -> 1 over this fraction of the run
    steps: int = 1000  # used when time_budget_s is None
    time_budget_s: float | None = None
    warmup: float = 0.02
    jpeg_mode: str = "real_diffgrad"
    noise_layers: tuple[str, ...] | None = None  # subset of training_noise_layers() names; None = all
    amp: bool = False  # bf16 autocast for the networks (DWT and attacks stay float32)
    seed: int = 0
    log_every: int = 50
    ckpt_every_s: float = 60.0


# ----------------------------------------------------------------------------------------------- data


def _read_image(path: Path) -> np.ndarray:
    try:
        import kornia_rs

        return np.asarray(kornia_rs.read_image_jpeg(str(path), "rgb")) if path.suffix.lower() in (
            ".jpg",
            ".jpeg",
        ) else np.asarray(kornia_rs.read_image(str(path)))[..., :3]
    except ImportError:
        from PIL import Image

        return np.asarray(Image.open(path).convert("RGB"))


def load_images(folder: str | Path, limit: int | None = None) -> list[torch.Tensor]:
    """All .jpg/.png images of ``folder`` (sorted) as uint8 tensors [3,H,W]."""
    paths = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    if limit is not None:
        paths = paths[:limit]
    if not paths:
        raise FileNotFoundError(f"no images in {folder}")
    return [torch.from_numpy(np.ascontiguousarray(_read_image(p))).permute(2, 0, 1).contiguous() for p in paths]


def random_crops(
    images: list[torch.Tensor], n: int, size: int, generator: torch.Generator, device: torch.device | str
) -> torch.Tensor:
    """n random ``size`` x ``size`` crops with random horizontal flips, float [n,3,size,size] in [0,1]."""
    idx = torch.randint(len(images), (n,), generator=generator).tolist()
    u = torch.rand(n, 3, generator=generator)
    out = []
    for i, k in enumerate(idx):
        img = images[k]
        h, w = img.shape[-2:]
        if h < size or w < size:
            img = F.interpolate(img[None].float(), size=(max(h, size), max(w, size)), mode="bilinear")[0]
            h, w = img.shape[-2:]
        y, x = int(u[i, 0] * (h - size + 1)), int(u[i, 1] * (w - size + 1))
        c = img[:, y : y + size, x : x + size]
        out.append(c.flip(-1) if u[i, 2] < 0.5 else c)
    return torch.stack(out).to(device, non_blocking=True).float() / 255.0


# --------------------------------------------------------------------------------------------- model


def embed(encoder: HiddenEncoder, imgs: torch.Tensor, msgs: torch.Tensor, psnr: float) -> torch.Tensor:
    """Watermark ``imgs`` [B,3,H,W] in [0,1]: residual rescaled per image to ``psnr`` dB, clamp (ST)."""
    delta = encoder(imgs, msgs).float()
    rms = delta.pow(2).mean(dim=(1, 2, 3), keepdim=True).add(1e-12).sqrt()
    return clamp_st(imgs + delta * (10.0 ** (-psnr / 20.0) / rms))


def _ramp(progress: float, frac: float) -> float:
    return 1.0 if frac <= 0 else min(1.0, progress / frac)


def _lr_factor(progress: float, warmup: float) -> float:
    if progress < warmup:
        return max(progress / warmup, 1e-3)
    return 0.5 * (1 + math.cos(math.pi * min(1.0, (progress - warmup) / max(1e-9, 1 - warmup)))) * 0.98 + 0.02


def _chunks(n: int, k: int) -> list[slice]:
    bounds = np.linspace(0, n, k + 1).round().astype(int)
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def _layers(cfg: TrainConfig) -> dict[str, NoiseLayer]:
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
    losses, accs = [], {}
    dev_type = x_w.device.type
    for (name, layer), sl in zip(layers.items(), _chunks(x_w.shape[0], len(layers))):
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


def _atomic_save(obj: Any, path: Path) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def train(
    cfg: TrainConfig,
    train_images: list[torch.Tensor],
    device: torch.device | str = "cpu",
    ckpt_path: str | Path | None = None,
    val_fn: Any = None,
    val_every_s: float = 120.0,
    verbose: bool = True,
) -> dict[str, Any]:
    """Pre-train encoder + decoder; resumes from ``ckpt_path`` if it exists.

    Returns:
        a state dict ``{"config", "step", "elapsed", "encoder", "decoder", "optimizer", "log", "val"}``
        (also what the checkpoint holds).
    """
    device = torch.device(device)
    torch.manual_seed(cfg.seed)
    enc = HiddenEncoder(cfg.num_bits, cfg.enc_blocks, cfg.channels).to(device)
    dec = HiddenDecoder(cfg.num_bits, cfg.dec_blocks, cfg.channels).to(device)
    params = list(enc.parameters()) + list(dec.parameters())
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    layers = _layers(cfg)
    state: dict[str, Any] = {"config": dataclasses.asdict(cfg), "step": 0, "elapsed": 0.0, "log": [], "val": []}
    ckpt_path = Path(ckpt_path) if ckpt_path else None
    if ckpt_path is not None and ckpt_path.exists():
        prev = torch.load(ckpt_path, map_location=device, weights_only=False)
        enc.load_state_dict(prev["encoder"])
        dec.load_state_dict(prev["decoder"])
        opt.load_state_dict(prev["optimizer"])
        state.update({k: prev[k] for k in ("step", "elapsed", "log", "val")})
        if verbose:
            print(f"[k={cfg.num_bits}] resumed at step {state['step']} ({state['elapsed']:.0f} s)", flush=True)
    gen = torch.Generator().manual_seed(cfg.seed * 1000 + state["step"])
    enc.train()
    dec.train()

    def progress() -> float:
        if cfg.time_budget_s is not None:
            return min(1.0, state["elapsed"] / cfg.time_budget_s)
        return min(1.0, state["step"] / max(1, cfg.steps))

    def save() -> None:
        if ckpt_path is not None:
            state.update(encoder=enc.state_dict(), decoder=dec.state_dict(), optimizer=opt.state_dict())
            _atomic_save(state, ckpt_path)

    t_last, t_ckpt, t_val = time.perf_counter(), time.perf_counter(), time.perf_counter()
    window: dict[str, list[float]] = {n: [] for n in layers}
    window["loss"] = []
    while progress() < 1.0:
        p = progress()
        for g in opt.param_groups:
            g["lr"] = cfg.lr * _lr_factor(p, cfg.warmup)
        strength = _ramp(p, cfg.noise_ramp)
        for layer in layers.values():
            layer.strength = strength
        psnr = cfg.psnr_start + (cfg.psnr_target - cfg.psnr_start) * _ramp(p, cfg.psnr_ramp)
        imgs = random_crops(train_images, cfg.batch_size, cfg.crop, gen, device)
        msgs = torch.randint(0, 2, (cfg.batch_size, cfg.num_bits), generator=gen).float().to(device)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=cfg.amp):
            x_w = embed(enc, imgs, msgs, psnr)
        loss, accs = _decode_chunks(dec, None, x_w, msgs, layers, gen, cfg.amp)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        state["step"] += 1
        for n, a in accs.items():
            window[n].append(a)
        window["loss"].append(loss.item())
        now = time.perf_counter()
        state["elapsed"] += now - t_last
        t_last = now
        if state["step"] % cfg.log_every == 0:
            entry = {"step": state["step"], "elapsed": round(state["elapsed"], 1), "lr": opt.param_groups[0]["lr"],
                     "psnr": psnr, "strength": strength}
            entry.update({f"acc_{n}" if n != "loss" else n: float(np.mean(v)) for n, v in window.items()})
            state["log"].append(entry)
            window = {n: [] for n in window}
            if verbose:
                print(f"[k={cfg.num_bits}] " + json.dumps({k: round(v, 4) if isinstance(v, float) else v
                                                          for k, v in entry.items()}), flush=True)
        if val_fn is not None and now - t_val > val_every_s:
            enc.eval(), dec.eval()
            v = val_fn(enc, dec, psnr)
            enc.train(), dec.train()
            v.update(step=state["step"], elapsed=round(state["elapsed"], 1))
            state["val"].append(v)
            if verbose:
                print(f"[k={cfg.num_bits}] val {json.dumps(v)}", flush=True)
            t_val = time.perf_counter()
            t_last = t_val  # validation time is not training time
        if now - t_ckpt > cfg.ckpt_every_s:
            save()
            t_ckpt = time.perf_counter()
            t_last = t_ckpt
    enc.eval()
    dec.eval()
    save()
    state.update(encoder=enc.state_dict(), decoder=dec.state_dict(), optimizer=opt.state_dict())
    state["modules"] = (enc, dec)
    return state


@torch.no_grad()
def fit_decoder_whitening(
    decoder: HiddenDecoder,
    images: list[torch.Tensor],
    device: torch.device | str,
    num_crops: int = 4000,
    crop_sizes: tuple[int, ...] = (96, 128, 192, 256),
    seed: int = 1,
    mode: str = "pca",
) -> tuple[WhiteningLayer, torch.Tensor]:
    """Fit PCA whitening on the decoder outputs of unmarked photos: every full image plus ``num_crops``
    random crops (sizes from ``crop_sizes``, random flips). Returns the layer and the raw outputs."""
    decoder.eval()
    gen = torch.Generator().manual_seed(seed)
    outs = [decoder(ll_subband(img[None].to(device).float() / 255.0)).float().cpu() for img in images]
    per = num_crops // len(crop_sizes)
    for s in crop_sizes:
        for i in range(0, per, 256):
            x = random_crops(images, min(256, per - i), s, gen, device)
            outs.append(decoder(ll_subband(x)).float().cpu())
    raw = torch.cat(outs)
    return WhiteningLayer(decoder.num_bits).fit(raw, mode=mode), raw


def finetune_encoder(
    encoder: HiddenEncoder,
    decoder: HiddenDecoder,
    whiten: WhiteningLayer,
    cfg: TrainConfig,
    train_images: list[torch.Tensor],
    device: torch.device | str,
    steps: int | None = None,
    time_budget_s: float | None = None,
    lr: float = 3e-4,
    verbose: bool = True,
) -> list[dict[str, float]]:
    """Train only the encoder against the frozen (eval-mode) decoder + whitening, at the target PSNR
    and full attack strength. Returns the log."""
    device = torch.device(device)
    decoder.eval()
    whiten.to(device)
    for p_ in decoder.parameters():
        p_.requires_grad_(False)
    encoder.train()
    opt = torch.optim.Adam(encoder.parameters(), lr=lr)
    layers = _layers(cfg)
    gen = torch.Generator().manual_seed(cfg.seed + 777)
    log, t0, step = [], time.perf_counter(), 0
    window: dict[str, list[float]] = {}
    while True:
        el = time.perf_counter() - t0
        prog = (step / steps) if steps is not None else el / (time_budget_s or 1.0)
        if prog >= 1.0:
            break
        for g in opt.param_groups:
            g["lr"] = lr * 0.5 * (1 + math.cos(math.pi * prog))
        imgs = random_crops(train_images, cfg.batch_size, cfg.crop, gen, device)
        msgs = torch.randint(0, 2, (cfg.batch_size, cfg.num_bits), generator=gen).float().to(device)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=cfg.amp):
            x_w = embed(encoder, imgs, msgs, cfg.psnr_target)
        loss, accs = _decode_chunks(decoder, whiten, x_w, msgs, layers, gen, cfg.amp)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        for n, a in accs.items():
            window.setdefault(n, []).append(a)
        window.setdefault("loss", []).append(loss.item())
        if step % cfg.log_every == 0:
            e = {"step": step, "elapsed": round(el, 1)}
            e.update({f"acc_{n}" if n != "loss" else n: float(np.mean(v)) for n, v in window.items()})
            log.append(e)
            window = {}
            if verbose:
                print(f"[k={cfg.num_bits} ft] " + json.dumps({k: round(v, 4) for k, v in e.items()}), flush=True)
    encoder.eval()
    for p_ in decoder.parameters():
        p_.requires_grad_(True)
    return log
