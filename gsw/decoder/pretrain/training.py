"""HiDDeN pre-training of the watermark decoder (with its encoder) under noise layers.

The pipeline (``benchmarks/train_decoder.py`` is the command-line entry point):

1. :func:`train` - encoder + decoder on random crops (and flips) of photos. The encoder's residual is
   rescaled per image to a fixed PSNR (ramped from ``psnr_start`` to ``psnr_target``), so the networks
   learn *where* to put the watermark, not how strong to make it. Each batch is split into one chunk per
   noise layer; the decoder reads the LL2 subband (:func:`gsw.decoder.dwt.ll_subband`) of each attacked
   chunk; the loss is the mean BCE-with-logits over chunks. Attack strengths ramp up over ``noise_ramp``
   of the run. Time- or step-budgeted, checkpointed, resumable; logs bit accuracy per noise layer.
2. :func:`train_multi` - the GPU-resident trainer that produced the shipped weights: every bit length at
   once on crops of a device-side image bank, device-only attacks; also the encoder-only fine-tune against
   frozen whitened decoders. :func:`fit_whitening_multi` then fits their whitening (ZCA, median-centred).
   Optionally (``MultiConfig.balance``) the decoder is also trained to be unbiased on unmarked crops of
   several sizes (:func:`balance_loss`), which whitening alone cannot give: the raw outputs of unmarked
   images shift with the image size, so a median fitted at one size leaves bits biased at another.

Only this subpackage is imported (no compiled extension), so it runs wherever torch does.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from gsw.decoder.dwt import ll_subband
from gsw.decoder.hidden import HiddenDecoder, HiddenEncoder, bit_accuracy
from gsw.attacks.layers import TRAINING_LAYER_NAMES, GpuAttacks, NoiseLayer, clamp_st, training_noise_layers
from gsw.mark.refine import scale_to_psnr
from gsw.decoder.whitening import WhiteningLayer
from gsw.decoder.zoo import atomic_torch_save

__all__ = [
    "TrainConfig",
    "balance_loss",
    "load_images",
    "random_crops",
    "embed",
    "train",
]


@dataclasses.dataclass
class TrainConfig:
    num_bits: int = 32
    channels: int = 64  # network width (64 for the shipped decoders; smaller only for tests)
    enc_blocks: int = 4
    dec_blocks: int = 8
    dec_norm: str = "standardize"  # HiddenDecoder input_norm
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
    return embed_scaled(encoder, imgs, msgs, psnr)


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
            atomic_torch_save(state, ckpt_path)

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


# ================================================================= fast trainer (GPU-resident, multi-k)
#
# The trainer above keeps the photos on the host, crops them in Python and runs real JPEG on the CPU:
# ~0.35 s/step on an H100, too slow to converge in a few minutes.  :func:`train_multi` instead
#
# * keeps the training photos on the device as one uint8 tensor and takes a batch of random crops (+ flips)
#   with one batched gather (:func:`image_bank`, :func:`bank_crops`);
# * trains several bit lengths at once: one encoder/decoder pair per bit length, all fed the same image
#   batch, one backward and one fused AdamW step for all of them;
# * attacks with device-only noise layers (:class:`GpuAttacks`, the ranges of
#   :func:`gsw.attacks.layers.training_noise_layers`, kornia's differentiable JPEG), random parameters
#   from device generators (per image) or a host ``random.Random`` (per batch), so a step never waits for
#   the device;
# * follows a curriculum: first ``clean_frac`` of the run without attacks at a strong watermark
#   (``psnr_start``), then the attack strength ramps to 1 and the PSNR to ``psnr_target``.


#: Sides of the unmarked crops seen by the balance loss and by the whitening fit.
UNMARKED_CROP_SIZES: tuple[int, ...] = (128, 192, 256, 320)
#: Whitening eigenvalue floor, relative to the largest eigenvalue (see :func:`fit_whitening_multi`).
WHITEN_EIG_FLOOR = 1e-3


@dataclasses.dataclass
class MultiConfig:
    bits: tuple[int, ...] = (32, 48, 64)
    channels: int = 64
    enc_blocks: int = 4
    dec_blocks: int = 8
    dec_norm: str = "standardize"  # HiddenDecoder input_norm
    crop: int = 128
    batch_size: int = 64  # per bit length; split into ``noise_chunks`` chunks, one random attack each
    noise_chunks: int = 2
    lr: float = 1e-3
    weight_decay: float = 0.0
    warmup: float = 0.03
    psnr_start: float = 22.0  # strong watermark while learning the code ...
    psnr_target: float = 30.0  # ... tightened to this
    clean_frac: float = 0.3  # no attacks before this fraction of the run
    noise_ramp_end: float = 0.6  # attack strength 0 -> 1 between clean_frac and this
    psnr_ramp_end: float = 0.8  # PSNR psnr_start -> psnr_target between clean_frac and this
    noise_layers: tuple[str, ...] = TRAINING_LAYER_NAMES
    steps: int = 1000  # used when time_budget_s is None
    time_budget_s: float | None = None
    amp: bool = True  # bf16 autocast for the networks (DWT, attacks and loss in float32)
    channels_last: bool = True
    seed: int = 0
    log_every: int = 100
    enc_down: int = 1  # the encoder works on the crop downsampled by this factor (see embed_scaled)
    templates: int = 0  # > 0: the encoder also adds learned periodic per-bit templates of this side (LL2 px)
    template_mlp: int = 0  # > 0: plus a nonlinear message -> tile branch of this width (TemplateEncoder mlp)
    template_refine: int = 0  # > 0: plus an image-adaptive conv refiner of this width (TemplateEncoder refine)
    view_warp: bool = False  # every sample also goes through GpuAttacks.view (ramped with the attack strength)
    balance: float = 0.0  # weight of the unmarked-balance loss (0 = off), see balance_loss
    balance_batch: int = 16  # unmarked crops per step and bit length for that loss
    balance_sizes: tuple[int, ...] = UNMARKED_CROP_SIZES  # their side, one drawn per step
    freeze_bn: bool = False  # decoder BatchNorm in eval mode (running statistics, frozen): for fine-tuning
    clean_chunk: bool = False  # the first of the noise_chunks is never attacked (the clean task weighs more)


class TemplateEncoder(torch.nn.Module):
    """A :class:`HiddenEncoder` plus learned per-bit on/off templates (a training aid for the decoder).

    residual = HiDDeN residual + sum_j (m_j P1_j + (1 - m_j) P0_j), where each P_j [3, t, t] is a periodic
    tile at the decoder's LL2 resolution, tiled over the image and upsampled x4 (bilinear).  The decoder
    averages over space, which makes it (nearly) translation invariant: it cannot tell a zero-mean pattern
    from its negative when that is a shift of it, so a bit is keyed as *which* of two patterns is present
    (an energy it can detect at any position), not as a pattern's sign.

    With ``mlp > 0`` a nonlinear branch adds ``MLP(2 m - 1)`` (two hidden layers of that width) to the tile:
    the sum of per-bit templates is linear in the message, so the decoder's nonlinear features mix bits
    (cross-talk no amplitude removes); the branch can shape the joint pattern of the whole message.  Its last
    layer starts at zero, so the branch can be added to a trained encoder without changing it.

    With ``refine > 0`` an image-adaptive refiner (``REFINE_DEPTH`` Conv3x3-GELU layers of that width, at the
    tiled pattern's resolution) reads the image (antialiased down to that resolution), the pattern and the
    broadcast message and adds a correction to the pattern: an image-agnostic pattern is read at most as well
    as one optimised tile per message (98 % of 64 bits on unseen photos, BENCHMARKS 5a), where optimising the
    pixels of each image reads 99.7 %.  Its last layer starts at zero as well.  (Measured: no gain over 360 s
    of fine-tuning at 64 bits, BENCHMARKS 5a item 5; :func:`gsw.mark.refine.refine_residual` is what
    adapts a residual to its image.)
    """

    REFINE_DEPTH = 6

    def __init__(self, hidden: HiddenEncoder, side: int = 8, scale: float = 1.0, mlp: int = 0,
                 refine: int = 0) -> None:
        super().__init__()
        self.hidden = hidden
        self.num_bits = hidden.num_bits
        self.templates = torch.nn.Parameter(torch.randn(2, hidden.num_bits, 3, side, side) * scale)
        self.mlp = None
        if mlp > 0:
            self.mlp = torch.nn.Sequential(torch.nn.Linear(self.num_bits, mlp), torch.nn.GELU(),
                                           torch.nn.Linear(mlp, mlp), torch.nn.GELU(),
                                           torch.nn.Linear(mlp, 3 * side * side))
            torch.nn.init.zeros_(self.mlp[-1].weight)
            torch.nn.init.zeros_(self.mlp[-1].bias)
        self.refine = None
        if refine > 0:
            layers: list[torch.nn.Module] = []
            cin = 6 + self.num_bits
            for _ in range(self.REFINE_DEPTH - 1):
                layers += [torch.nn.Conv2d(cin, refine, 3, 1, 1), torch.nn.GELU()]
                cin = refine
            layers.append(torch.nn.Conv2d(cin, 3, 3, 1, 1))
            torch.nn.init.zeros_(layers[-1].weight)
            torch.nn.init.zeros_(layers[-1].bias)
            self.refine = torch.nn.Sequential(*layers)

    @torch.no_grad()
    def load_grown_state_dict(self, state: dict[str, torch.Tensor], seed: int = 0) -> None:
        """Load the state of a smaller template encoder so that this one computes the same residual.

        Templates (and an ``mlp`` branch's output tile) whose side divides this one's are tiled (the same
        periodic pattern); a missing ``mlp`` branch keeps its zero output layer; a narrower one is widened:
        new hidden units get random inputs and zero outputs, and old units never read new ones; a missing
        ``refine`` branch keeps its zero output layer.  Anything else must match exactly.
        """
        state = dict(state)
        side, t = state["templates"].shape[-1], self.templates.shape[-1]
        if t % side:
            raise ValueError(f"templates of side {side} cannot grow to side {t}")
        r = t // side
        state["templates"] = state["templates"].repeat(1, 1, 1, r, r)
        if "mlp.4.weight" in state:  # the branch's output is a tile too: repeat its rows the same way
            w, b = state["mlp.4.weight"], state["mlp.4.bias"]
            state["mlp.4.weight"] = w.view(3, side, side, -1).repeat(1, r, r, 1).reshape(3 * t * t, -1)
            state["mlp.4.bias"] = b.view(3, side, side).repeat(1, r, r).reshape(-1)
        if "mlp.0.weight" in state:
            if self.mlp is None:
                raise ValueError("the state has an mlp branch, this encoder has none")
            h, width = state["mlp.0.weight"].shape[0], self.mlp[0].out_features
            if width < h:
                raise ValueError(f"an mlp branch of width {h} cannot shrink to {width}")
            gen = torch.Generator().manual_seed(seed)
            new = {n: p.detach().clone() for n, p in self.mlp.state_dict().items()}
            k = new["0.weight"].shape[1]
            new["0.weight"] = torch.randn(width, k, generator=gen) / k**0.5
            new["0.weight"][:h] = state["mlp.0.weight"]
            new["2.weight"] = torch.randn(width, width, generator=gen) / width**0.5
            new["2.weight"][:h] = 0.0
            new["2.weight"][:h, :h] = state["mlp.2.weight"]
            new["4.weight"] = torch.zeros_like(new["4.weight"])
            new["4.weight"][:, :h] = state["mlp.4.weight"]
            for b in ("0.bias", "2.bias"):
                new[b] = torch.zeros(width)
                new[b][:h] = state[f"mlp.{b}"]
            new["4.bias"] = state["mlp.4.bias"]
            state.update({f"mlp.{n}": v for n, v in new.items()})
        missing, unexpected = self.load_state_dict(state, strict=False)
        if "refine.0.weight" in state and self.refine is None:
            raise ValueError("the state has a refine branch, this encoder has none")
        if unexpected or any(not n.startswith(("mlp.", "refine.")) for n in missing):
            raise ValueError(f"state does not match (missing {missing}, unexpected {unexpected})")

    def forward(self, imgs: torch.Tensor, msgs: torch.Tensor) -> torch.Tensor:
        h, w = imgs.shape[-2:]
        hs, ws = -(-h // 4), -(-w // 4)
        t = self.templates.shape[-1]
        m = msgs.to(self.templates.dtype)
        pat = torch.einsum("bk,kchw->bchw", m, self.templates[1]) + torch.einsum("bk,kchw->bchw", 1.0 - m,
                                                                                   self.templates[0])
        pat = pat / math.sqrt(self.num_bits)
        if self.mlp is not None:
            pat = pat + self.mlp(m * 2.0 - 1.0).view(-1, 3, t, t).to(pat.dtype)
        pat = pat.repeat(1, 1, -(-hs // t), -(-ws // t))[..., :hs, :ws]
        shift = [int(v) for v in torch.randint(0, t, (2,))] if self.training else [0, 0]
        pat = torch.roll(pat, shift, dims=(-2, -1))  # random phase while training: nothing to learn from it
        if self.refine is not None:
            small = F.interpolate(imgs, size=(hs, ws), mode="bilinear", align_corners=False, antialias=True)
            mb = (m * 2.0 - 1.0)[:, :, None, None].expand(-1, -1, hs, ws)
            x = torch.cat([small.to(pat.dtype) * 2.0 - 1.0, pat, mb], dim=1)
            pat = pat + self.refine(x).to(pat.dtype)
        pat = F.interpolate(pat, size=(hs * 4, ws * 4), mode="bilinear", align_corners=False)[..., :h, :w]
        return self.hidden(imgs, msgs) + pat.to(imgs.dtype if not torch.is_autocast_enabled() else pat.dtype)


def make_encoder(num_bits: int, cfg: MultiConfig) -> HiddenEncoder | TemplateEncoder:
    """The pre-training encoder ``cfg`` describes: a :class:`HiddenEncoder`, wrapped in a
    :class:`TemplateEncoder` when ``cfg.templates > 0`` (with its ``mlp`` / ``refine`` branches when
    ``cfg.template_mlp`` / ``cfg.template_refine`` > 0)."""
    enc = HiddenEncoder(num_bits, cfg.enc_blocks, cfg.channels)
    if cfg.templates <= 0:
        return enc
    return TemplateEncoder(enc, cfg.templates, mlp=cfg.template_mlp, refine=cfg.template_refine)


def load_run_encoder(run: str | Path, num_bits: int, key: str = "encoder_ft") -> tuple[torch.nn.Module, MultiConfig]:
    """The encoder ``key`` of a ``benchmarks/train_decoder.py`` run (CPU, eval mode) and the run's config.

    Reads ``k{num_bits}.json`` for the architecture and the weights from ``k{num_bits}.pt`` (full, or a
    ``--half`` checkpoint whose encoders are float16), or, for ``encoder_ft``, from a float16 file
    ``k{num_bits}.encoder_ft16.pt`` beside the json (what ``--ft-half`` wrote before ``--half`` replaced it)."""
    run = Path(run)
    meta = json.loads((run / f"k{num_bits}.json").read_text())
    fields = {f.name for f in dataclasses.fields(MultiConfig)}
    cfg = MultiConfig(**{n: v for n, v in meta["config"].items() if n in fields})
    src = run / f"k{num_bits}.pt"
    if not src.exists() and key == "encoder_ft":
        src = run / f"k{num_bits}.encoder_ft16.pt"
    if not src.exists():
        raise FileNotFoundError(f"{run}: neither k{num_bits}.pt nor a float16 encoder file")
    state = torch.load(src, map_location="cpu", weights_only=False)[key]
    enc = make_encoder(num_bits, cfg)
    enc.load_state_dict({n: v.float() if v.is_floating_point() else v for n, v in state.items()})
    return enc.eval(), cfg


def embed_scaled(encoder: HiddenEncoder, imgs: torch.Tensor, msgs: torch.Tensor, psnr: float,
                 down: int = 1) -> torch.Tensor:
    """:func:`embed` with the encoder run on ``imgs`` downsampled by ``down`` (antialiased bilinear) and its
    residual upsampled back (bilinear) before the rescale to ``psnr``: the watermark then lives in the low
    frequencies that the decoder's LL2 input keeps, and the encoder costs ``down**2`` times less."""
    return clamp_st(imgs + scale_to_psnr(encoder_residual(encoder, imgs, msgs, down), psnr))


def encoder_residual(encoder: HiddenEncoder, imgs: torch.Tensor, msgs: torch.Tensor, down: int = 1) -> torch.Tensor:
    """The unscaled residual [B,3,H,W] (float32) that :func:`embed_scaled` rescales: the encoder run on
    ``imgs`` downsampled by ``down`` (antialiased bilinear), its output upsampled back (bilinear)."""
    if down <= 1:
        return encoder(imgs, msgs).float()
    h, w = imgs.shape[-2:]
    small = F.interpolate(imgs, size=(max(4, round(h / down)), max(4, round(w / down))), mode="bilinear",
                          align_corners=False, antialias=True)
    return F.interpolate(encoder(small, msgs).float(), size=(h, w), mode="bilinear", align_corners=False)


def image_bank(images: list[torch.Tensor], device: torch.device | str) -> torch.Tensor:
    """uint8 [N,3,H,W] on ``device``: portrait photos transposed to landscape, all cropped (centre) to the
    smallest common size."""
    ims = [img if img.shape[-2] <= img.shape[-1] else img.transpose(-1, -2) for img in images]
    h = min(i.shape[-2] for i in ims)
    w = min(i.shape[-1] for i in ims)
    out = []
    for i in ims:
        y0, x0 = (i.shape[-2] - h) // 2, (i.shape[-1] - w) // 2
        out.append(i[:, y0 : y0 + h, x0 : x0 + w])
    return torch.stack(out).contiguous().to(device)


def bank_crops(bank: torch.Tensor, n: int, size: int, gen: torch.Generator,
               channels_last: bool = False) -> torch.Tensor:
    """n random ``size`` x ``size`` crops of the bank with random horizontal and vertical flips, one gather;
    float [n,3,size,size] in [0,1] on the bank's device."""
    dev = bank.device
    N, _, H, W = bank.shape
    u = torch.rand(n, 5, device=dev, generator=gen)
    k = (u[:, 0] * N).long().clamp_max(N - 1)
    oy = (u[:, 1] * (H - size + 1)).long().clamp_max(H - size)
    ox = (u[:, 2] * (W - size + 1)).long().clamp_max(W - size)
    ar = torch.arange(size, device=dev)
    ry = oy[:, None] + torch.where(u[:, 3:4] < 0.5, ar, size - 1 - ar)  # vertical flip
    rx = ox[:, None] + torch.where(u[:, 4:5] < 0.5, ar, size - 1 - ar)  # horizontal flip
    c = bank[k[:, None, None], :, ry[:, :, None], rx[:, None, :]]  # [n,size,size,3] (NHWC)
    x = c.permute(0, 3, 1, 2).float() / 255.0
    return x.contiguous(memory_format=torch.channels_last) if channels_last else x.contiguous()


def _sched(cfg: MultiConfig, p: float) -> tuple[float, float, float]:
    """(lr factor, attack strength, PSNR) at progress p in [0,1]."""
    lr = _lr_factor(p, cfg.warmup)
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
    if on:
        for mod in m.modules():  # only the convolutions (a TemplateEncoder's templates are 5-D)
            if isinstance(mod, torch.nn.Conv2d):
                mod.to(memory_format=torch.channels_last)
    return m


def train_multi(
    cfg: MultiConfig,
    bank: torch.Tensor,
    *,
    encoders: list[HiddenEncoder] | None = None,
    decoders: list[HiddenDecoder] | None = None,
    whitenings: list[WhiteningLayer] | None = None,
    finetune_encoders: bool = False,
    val_fn: Any = None,
    val_every_s: float = 60.0,
    verbose: bool = True,
    tag: str = "",
) -> dict[str, Any]:
    """Train one encoder/decoder pair per bit length in ``cfg.bits`` on crops of ``bank`` (from
    :func:`image_bank`, on the training device).

    With ``finetune_encoders=True`` (pass trained ``encoders``, ``decoders`` and ``whitenings``) only the
    encoders are trained, against the frozen eval-mode decoders followed by their whitening, at
    ``psnr_target`` and full attack strength from the start (the situation of the 3DGS embedding).

    Returns ``{"encoders", "decoders", "step", "elapsed", "log", "val", "steps_per_s"}``.
    """
    dev = bank.device
    torch.manual_seed(cfg.seed)
    if encoders is None:
        encoders = [make_encoder(k, cfg) for k in cfg.bits]
    if decoders is None:
        decoders = [HiddenDecoder(k, cfg.dec_blocks, cfg.channels, cfg.dec_norm) for k in cfg.bits]
    encoders = [_to_cl(e.to(dev), cfg.channels_last) for e in encoders]
    decoders = [_to_cl(d.to(dev), cfg.channels_last) for d in decoders]
    if finetune_encoders:
        assert whitenings is not None
        whitenings = [w.to(dev) for w in whitenings]
        for d in decoders:
            d.eval().requires_grad_(False)
        params = [p for e in encoders for p in e.parameters()]
    else:
        whitenings = None
        for d in decoders:
            _train_mode(d, cfg.freeze_bn)
        params = [p for m in (*encoders, *decoders) for p in m.parameters()]
    for e in encoders:
        e.train()
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay,
                            **({"fused": True} if dev.type == "cuda" else {}))
    gen = torch.Generator(device=dev).manual_seed(cfg.seed * 7919 + (1 if finetune_encoders else 0))
    attacks = GpuAttacks(dev, cfg.seed + (101 if finetune_encoders else 0))
    names = list(cfg.noise_layers)
    M, L = len(cfg.bits), len(names)
    acc_sum = torch.zeros(M, L, device=dev)
    cnt = [0] * L
    loss_sum = torch.zeros((), device=dev)
    bal_sum = torch.zeros(M, device=dev)
    n_loss = 0
    log: list[dict[str, Any]] = []
    vals: list[dict[str, Any]] = []
    step, elapsed = 0, 0.0
    t_last = t_val = time.perf_counter()
    t_start = t_last

    def progress() -> float:
        if cfg.time_budget_s is not None:
            return min(1.0, elapsed / cfg.time_budget_s)
        return min(1.0, step / max(1, cfg.steps))

    B = cfg.batch_size
    chunks = _chunks(B, max(1, cfg.noise_chunks))
    balance_on = cfg.balance > 0 and not finetune_encoders
    while progress() < 1.0:
        p = progress()
        if finetune_encoders:
            lrf, strength, psnr = 0.5 * (1 + math.cos(math.pi * p)), 1.0, cfg.psnr_target
        else:
            lrf, strength, psnr = _sched(cfg, p)
        for g in opt.param_groups:
            g["lr"] = cfg.lr * lrf
        imgs = bank_crops(bank, B, cfg.crop, gen, cfg.channels_last)
        if strength <= 0.0:
            picks = [names.index("identity") if "identity" in names else 0] * len(chunks)
        else:
            picks = [attacks.rng.randrange(L) for _ in chunks]
            if cfg.clean_chunk and "identity" in names:
                picks[0] = names.index("identity")
        total = 0.0
        cover_size = min(attacks.rng.choice(cfg.balance_sizes), *bank.shape[-2:]) if balance_on else 0
        for m, k in enumerate(cfg.bits):
            msgs = torch.randint(0, 2, (B, k), device=dev, generator=gen).float()
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=cfg.amp):
                x_w = embed_scaled(encoders[m], imgs, msgs, psnr, cfg.enc_down)
            for sl, li in zip(chunks, picks):
                y = attacks.view(x_w[sl], strength) if cfg.view_warp else x_w[sl]
                ll = _decoder_input(attacks.apply(names[li], y, strength), cfg.channels_last)
                with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=cfg.amp):
                    logits = decoders[m](ll)
                logits = logits.float()
                if whitenings is not None:
                    logits = whitenings[m](logits)
                total = total + F.binary_cross_entropy_with_logits(logits, msgs[sl]) * (
                    (sl.stop - sl.start) / B)
                acc_sum[m, li] += bit_accuracy(logits.detach(), msgs[sl]).mean()
            if balance_on:
                # unmarked crops of a random size, decoded as at inference (eval-mode BatchNorm: in train
                # mode the batch statistics would hide exactly the shift that biases the bits)
                cover = bank_crops(bank, cfg.balance_batch, cover_size, gen, cfg.channels_last)
                cover = attacks.view(cover, strength) if cfg.view_warp else cover
                ll = _decoder_input(cover, cfg.channels_last)
                decoders[m].eval()
                with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=cfg.amp):
                    u = decoders[m](ll)
                _train_mode(decoders[m], cfg.freeze_bn)
                bal = balance_loss(u)
                total = total + cfg.balance * bal
                bal_sum[m] += bal.detach()
        for li in picks:
            cnt[li] += 1
        opt.zero_grad(set_to_none=True)
        total.backward()
        if not finetune_encoders:
            for m in range(M):
                torch.nn.utils.clip_grad_norm_(
                    list(encoders[m].parameters()) + list(decoders[m].parameters()), 1.0, foreach=True)
        opt.step()
        loss_sum += total.detach() / M
        n_loss += 1
        step += 1
        now = time.perf_counter()
        elapsed += now - t_last
        t_last = now
        if step % cfg.log_every == 0 or progress() >= 1.0:
            accs = (acc_sum / torch.tensor([max(1, c) for c in cnt], device=dev)).tolist()  # sync
            now = time.perf_counter()
            elapsed += now - t_last
            t_last = now
            entry: dict[str, Any] = {"step": step, "elapsed": round(elapsed, 1), "lr": cfg.lr * lrf,
                                     "psnr": round(psnr, 2), "strength": round(strength, 3),
                                     "loss": float(loss_sum) / max(1, n_loss)}
            for m, k in enumerate(cfg.bits):
                entry[f"k{k}"] = {names[li]: round(accs[m][li], 4) for li in range(L) if cnt[li]}
            if balance_on:
                entry["balance"] = {f"k{k}": round(float(bal_sum[m]) / max(1, n_loss), 5)
                                    for m, k in enumerate(cfg.bits)}
            log.append(entry)
            acc_sum.zero_()
            bal_sum.zero_()
            loss_sum.zero_()
            cnt, n_loss = [0] * L, 0
            if verbose:
                brief = " ".join(f"k{k}:" + "/".join(f"{v:.3f}" for v in entry[f"k{k}"].values())
                                 for k in cfg.bits)
                print(f"[{tag}step {step} {elapsed:.0f}s {step / max(elapsed, 1e-9):.2f} it/s psnr {psnr:.1f} "
                      f"str {strength:.2f} loss {entry['loss']:.4f}] {brief}", flush=True)
        if val_fn is not None and time.perf_counter() - t_val > val_every_s:
            for mod in (*encoders, *decoders):
                mod.eval()
            v = val_fn(encoders, decoders, psnr)
            for e in encoders:
                e.train()
            if not finetune_encoders:
                for d in decoders:
                    _train_mode(d, cfg.freeze_bn)
            v.update(step=step, elapsed=round(elapsed, 1))
            vals.append(v)
            if verbose:
                print(f"[{tag}val] {json.dumps(v)}", flush=True)
            t_val = time.perf_counter()
            t_last = t_val  # validation time is not training time
    if dev.type == "cuda":
        torch.cuda.synchronize()
    for mod in (*encoders, *decoders):
        mod.eval()
    if finetune_encoders:
        for d in decoders:
            d.requires_grad_(True)
    return {"encoders": encoders, "decoders": decoders, "step": step, "elapsed": elapsed, "log": log,
            "val": vals, "steps_per_s": step / max(elapsed, 1e-9), "wall_s": time.perf_counter() - t_start}


@torch.no_grad()
def fit_whitening_multi(
    decoders: list[HiddenDecoder],
    images: list[torch.Tensor],
    bank: torch.Tensor,
    num_crops: int = 4000,
    crop_sizes: tuple[int, ...] = UNMARKED_CROP_SIZES,
    seed: int = 1,
    mode: str = "zca",
    center: str = "median",
    eps: float = WHITEN_EIG_FLOOR,
) -> tuple[list[WhiteningLayer], int]:
    """Whitening of each (eval-mode) decoder on the same unmarked inputs: every full photo of ``images``
    and its mirror image, plus ``num_crops`` random crops (+ flips) of ``bank`` in ``crop_sizes``.
    ``mode`` / ``center`` / ``eps`` as in :meth:`WhiteningLayer.fit`; the default ``eps`` (relative to the
    largest eigenvalue) caps the gain at ~30x the top direction's: a decoder trained with the balance loss
    can have a dead output direction (eigenvalue ~1e-11) that an unregularised inverse square root would
    amplify by ~1e5, turning float rounding (TF32 on GPUs) into bit flips.  Returns the layers (on the CPU) and the
    number of samples."""
    dev = bank.device
    for d in decoders:
        d.eval()
    gen = torch.Generator(device=dev).manual_seed(seed)
    outs: list[list[torch.Tensor]] = [[] for _ in decoders]
    for img in images:
        x = img[None].to(dev).float() / 255.0
        ll = ll_subband(torch.cat([x, x.flip(-1)]))
        for i, d in enumerate(decoders):
            outs[i].append(d(ll).float().cpu())
    per = num_crops // len(crop_sizes)
    for s in crop_sizes:
        for i0 in range(0, per, 250):
            ll = ll_subband(bank_crops(bank, min(250, per - i0), s, gen))
            for i, d in enumerate(decoders):
                outs[i].append(d(ll).float().cpu())
    layers = [WhiteningLayer(d.num_bits).fit(torch.cat(o), mode=mode, center=center, eps=eps)
              for d, o in zip(decoders, outs)]
    return layers, int(torch.cat(outs[0]).shape[0])
