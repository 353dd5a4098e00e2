"""Pre-training encoders and how a watermark is written with them.

* :class:`TemplateEncoder` - a :class:`~gsw.decoder.hidden.HiddenEncoder` plus learned per-bit on/off
  templates (a training aid); :func:`make_encoder` builds the encoder a :class:`MultiConfig` describes.
* :func:`embed_scaled` - the encoder's residual (:func:`encoder_residual`, optionally computed at a lower
  resolution) rescaled per image to a PSNR and added with a straight-through clamp.
* :func:`load_run_encoder`, :func:`encoder_state`, :func:`to_half` - encoders of a pre-training run folder.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import torch
import torch.nn.functional as F

from gsw.attacks.layers import clamp_st
from gsw.decoder.hidden import HiddenEncoder, scale_to_psnr
from gsw.decoder.pretrain.config import MultiConfig

__all__ = ["TemplateEncoder", "embed", "embed_scaled", "encoder_residual", "encoder_state", "load_run_encoder",
           "make_encoder", "to_half"]


def embed(encoder: HiddenEncoder, imgs: torch.Tensor, msgs: torch.Tensor, psnr: float) -> torch.Tensor:
    """Watermark ``imgs`` [B,3,H,W] in [0,1] with ``msgs`` [B,k]: the encoder's residual rescaled per image to
    ``psnr`` dB, added, clamped to [0,1] with a straight-through gradient."""
    return embed_scaled(encoder, imgs, msgs, psnr)


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
        """imgs [B,3,H,W] in [0,1], msgs [B,k] in {0,1} -> residual [B,3,H,W] (HiDDeN part + tiled pattern)."""
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
    """The encoder ``key`` of a pre-training run folder (``gsw decoder train``; CPU, eval mode) and the
    run's config.

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


def encoder_state(encoder: torch.nn.Module, half: bool) -> dict[str, torch.Tensor]:
    """The encoder's state dict on the CPU, floating tensors in float16 when ``half``."""
    return {n: (v.half() if half and v.is_floating_point() else v).cpu() for n, v in encoder.state_dict().items()}


def to_half(encoder: torch.nn.Module) -> None:
    """Round the encoder's weights to float16 in place (they stay float32 tensors)."""
    encoder.load_state_dict(encoder_state(encoder, True))
