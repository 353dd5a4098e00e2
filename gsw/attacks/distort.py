"""Differentiable model distortions for train-time sampling (what happens to a 3DGS after it leaves us).

The evaluation's model attacks (:mod:`gsw.attacks.model`) return detached copies; these keep the graph so
that the clean parameters learn a message that survives them. The export quantisers are straight-through:
the forward pass equals a real export and reload (:func:`splat_st`: antimatter15 ``.splat`` through
:mod:`gsw.io.splat`; :func:`spz_st`: Niantic ``.spz`` version 3 with its default precisions through
:mod:`gsw.io.spz`; :func:`quantize_st`: the 8-bit per-column quantisation of
:func:`gsw.attacks.model.quantize`), the gradient is the identity on every parameter the format keeps
(``.splat`` drops the SH rest: no gradient reaches it). :func:`distort` draws one of :data:`DISTORTIONS`.

Every function takes and returns :class:`~gsw.gaussians.Gaussians` (any device; the quantisation runs in
float64, as the codecs do, and is cast back to the model's dtype).
"""

from __future__ import annotations

import math
import random

import numpy as np
import torch
from torch import Tensor

from gsw.gaussians import Gaussians

__all__ = ["DISTORTIONS", "distort", "noise", "sh0", "splat_st", "spz_st", "quantize_st"]

_SQRT1_2 = math.sqrt(0.5)


def _st(x: Tensor, forward: Tensor) -> Tensor:
    """``forward`` in the forward pass, the identity gradient to ``x``."""
    return x + (forward.to(x.dtype) - x).detach()


def _u8(x: Tensor) -> Tensor:
    return torch.round(x).clamp(0, 255)


def noise(g: Gaussians, sigma: float = 0.1, generator: torch.Generator | None = None) -> Gaussians:
    """``N(0, sigma^2)`` on every raw parameter but the positions (the evaluation's
    :func:`gsw.attacks.model.parameter_noise_attributes`), drawn on the model's device from a generator seeded by
    one draw of the CPU ``generator`` (reproducible per device; no host-side noise tensors)."""
    device = g.means.device
    seed = int(torch.randint(0, 2**62, (1,), generator=generator))
    local = torch.Generator(device=device).manual_seed(seed)

    def noisy(t: Tensor) -> Tensor:
        return t + sigma * torch.randn(t.shape, generator=local, device=device, dtype=t.dtype)

    return Gaussians(g.means, noisy(g.log_scales), noisy(g.quats), noisy(g.opacity_logits), noisy(g.sh))


def sh0(g: Gaussians) -> Gaussians:
    """The view-dependent SH zeroed (what degree-0 viewers and the ``.splat`` format show)."""
    return Gaussians(g.means, g.log_scales, g.quats, g.opacity_logits,
                     torch.cat([g.sh[:, :1], torch.zeros_like(g.sh[:, 1:])], dim=1))


def _logit_of_byte(b: Tensor) -> Tensor:
    from gsw.io.splat import ALPHA_EPS

    return torch.logit((b / 255.0).clamp(ALPHA_EPS, 1.0 - ALPHA_EPS))


def splat_st(g: Gaussians) -> Gaussians:
    """Straight-through ``.splat`` export and reload (:func:`gsw.io.splat.save_splat` / ``load_splat``).

    Forward: float32 positions and linear scales (at least ``SCALE_RANGE[0]``), colour and alpha as bytes ``round(255 v)``, the unit
    quaternion as bytes ``round(128 q + 128)``, SH degree 0 (the format keeps no SH rest).

    Args:
        g: the model (differentiable).

    Returns:
        Gaussians with SH degree 0 whose values equal ``load_splat(save_splat(g))``.
    """
    from gsw.gaussians import rgb_to_sh_dc, sh_dc_to_rgb
    from gsw.io.splat import SCALE_RANGE

    d = g.detach().to(dtype=torch.float64)
    scales = d.log_scales.exp().float().clamp_min(SCALE_RANGE[0]).double().log()  # as save_splat writes them
    rgb = _u8(sh_dc_to_rgb(d.sh[:, 0]) * 255.0) / 255.0
    alpha = _u8(d.opacities * 255.0)
    rot = (_u8(d.rotations * 128.0 + 128.0) - 128.0) / 128.0
    return Gaussians(_st(g.means, d.means.float()), _st(g.log_scales, scales), _st(g.quats, rot),
                     _st(g.opacity_logits, _logit_of_byte(alpha)), _st(g.sh[:, :1], rgb_to_sh_dc(rgb)[:, None]))


def _smallest_three(q: Tensor) -> Tensor:
    """``[N, 4]`` unit quaternions ``(x, y, z, w)`` through SPZ v3's smallest-three packing and back."""
    n = q.shape[0]
    rows = torch.arange(n, device=q.device)
    largest = q.abs().argmax(dim=1)
    q = q * torch.where(q[rows, largest] < 0, -1.0, 1.0).to(q)[:, None]
    magnitude = torch.floor(511.0 * q.abs() / _SQRT1_2 + 0.5).clamp_max(511) / 511.0 * _SQRT1_2
    value = magnitude * torch.where(q < 0, -1.0, 1.0).to(q)
    value[rows, largest] = 0.0
    value[rows, largest] = (1.0 - (value * value).sum(1)).clamp_min(0.0).sqrt()
    return value


def _spz_sh(values: Tensor, bits: int) -> Tensor:
    bucket = 1 << (8 - bits)
    b = (torch.round(values * 128.0) + 128.0).clamp(0, 255)
    b = (torch.div(b + bucket // 2, bucket, rounding_mode="floor") * bucket).clamp(0, 255)
    return (b - 128.0) / 128.0


def spz_st(g: Gaussians, sh1_bits: int = 5, sh_rest_bits: int = 4) -> Gaussians:
    """Straight-through ``.spz`` (version 3, RUB axes) export and reload (:func:`gsw.io.spz.save_spz` /
    ``load_spz`` with their defaults).

    Forward: positions in 24-bit fixed point (12 fractional bits, fewer for large scenes), alpha, colour
    (``f_dc * 0.15 * 255 + 127.5``) and log-scales (``(s + 10) * 16``) as bytes, rotations by
    smallest-three (3 x 9 bits), SH rest as bytes rounded to ``sh1_bits`` / ``sh_rest_bits``.

    Args:
        g: the model (differentiable).
        sh1_bits: precision of the degree-1 SH coefficients (as :func:`gsw.io.spz.save_spz`).
        sh_rest_bits: precision of the degree-2/3 coefficients.

    Returns:
        Gaussians whose values equal ``load_spz(save_spz(g))`` (up to float32 rounding).
    """
    from gsw.io.spz import SH_FLIP_RUB_RDF, SPZ_COLOR_SCALE, _fractional_bits

    d = g.detach().to(dtype=torch.float64)
    largest = float(d.means.abs().max()) if len(d) else 0.0
    frac = _fractional_bits(np.array([largest]), None, "<in memory>")
    means = torch.round(d.means * (1 << frac)) / (1 << frac)
    alpha = _u8(d.opacities * 255.0)
    colour = (_u8(d.sh[:, 0] * (SPZ_COLOR_SCALE * 255.0) + 127.5) / 255.0 - 0.5) / SPZ_COLOR_SCALE
    log_scales = _u8((d.log_scales + 10.0) * 16.0) / 16.0 - 10.0
    wxyz = d.quats.clone()
    wxyz[wxyz.norm(dim=1) == 0] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=wxyz.dtype, device=wxyz.device)
    flip_q = torch.tensor([1.0, 1.0, -1.0, -1.0], dtype=wxyz.dtype, device=wxyz.device)
    wxyz = wxyz / wxyz.norm(dim=1, keepdim=True) * flip_q
    xyzw = _smallest_three(wxyz[:, [1, 2, 3, 0]])
    quats = xyzw[:, [3, 0, 1, 2]] * flip_q
    k = d.sh.shape[1]
    flip_sh = torch.tensor(SH_FLIP_RUB_RDF[: k - 1], dtype=d.sh.dtype, device=d.sh.device)[:, None]
    rest = d.sh[:, 1:] * flip_sh
    rest = torch.cat([_spz_sh(rest[:, :3], sh1_bits), _spz_sh(rest[:, 3:], sh_rest_bits)], dim=1) * flip_sh
    sh = torch.cat([colour[:, None], rest], dim=1)
    return Gaussians(_st(g.means, means), _st(g.log_scales, log_scales), _st(g.quats, quats),
                     _st(g.opacity_logits, _logit_of_byte(alpha)), _st(g.sh, sh))


def quantize_st(g: Gaussians, bits: int = 8) -> Gaussians:
    """Straight-through :func:`gsw.attacks.model.quantize` (per-column min-max, ``bits`` per value)."""
    from gsw.attacks.model import quantize

    q = quantize(g.detach(), bits)
    return Gaussians(*(_st(getattr(g, f), getattr(q, f)) for f in ("means", "log_scales", "quats", "opacity_logits",
                                                                    "sh")))


#: Train-time model distortions by name.
DISTORTIONS: tuple[str, ...] = ("noise", "sh0", "splat", "spz", "8bit")


def distort(g: Gaussians, kinds: tuple[str, ...], rng: random.Random, generator: torch.Generator,
            sigma: float = 0.1) -> tuple[str, Gaussians]:
    """One distortion of ``kinds`` (``kinds[int(rng.random() * len(kinds))]``) applied to ``g``, differentiably.

    Args:
        g: the model.
        kinds: names from :data:`DISTORTIONS`.
        rng: the choice.
        generator: the noise's seed (a CPU generator).
        sigma: std of ``noise``.

    Returns:
        ``(name, distorted model)``.
    """
    unknown = [k for k in kinds if k not in DISTORTIONS]
    if unknown or not kinds:
        raise ValueError(f"unknown model distortions {unknown or kinds}; choose from {DISTORTIONS}")
    kind = kinds[int(rng.random() * len(kinds))]
    if kind == "noise":
        return kind, noise(g, sigma, generator)
    return kind, {"sh0": sh0, "splat": splat_st, "spz": spz_st, "8bit": quantize_st}[kind](g)
