"""2-D discrete wavelet transform (bior4.4 = CDF 9/7, periodization) in pure PyTorch.

This is the project's single DWT: the decoder input (the level-2 LL subband), the subband loss of the
embedding and the extraction all go through :func:`dwt2` / :func:`ll_subband`.

Choice (matches the official 3D-GSW code, which uses ``pytorch_wavelets`` with ``bior4.4``, ``J=2``,
``mode='periodization'``):

* **Wavelet** ``bior4.4`` (the Cohen-Daubechies-Feauveau 9/7 pair): a 9-tap analysis low-pass ``h`` and a
  7-tap synthesis low-pass ``g``.  The filters are *derived* at import time from their published
  definition (below), in float64, and checked against the published decimals in the tests.
* **Boundary** periodization: the signal is treated as periodic, so a length-``N`` signal gives
  ``N/2`` approximation and ``N/2`` detail coefficients and the transform is exactly invertible.
* **Alignment** (same as PyWavelets' ``periodization`` mode): ``a[o] = sum_m h[m] x[2o + m]`` (low-pass
  centred on even samples) and ``d[o] = sum_m h1[m] x[2o + 1 + m]`` (high-pass centred on odd samples).
* **Sizes not divisible by ``2**levels``**: the image is *reflect-padded* at the bottom and right to the
  next multiple of ``2**levels`` before the transform (``torch.nn.functional.pad(mode='reflect')``, which
  does not repeat the edge sample; if the image is too small for reflection, replicate padding is used).
  :func:`idwt2` returns the padded size; pass ``size=(H, W)`` to crop back.

Filter definition (Daubechies, *Ten Lectures on Wavelets*, sec. 8.3; Cohen, Daubechies & Feauveau 1992):
with ``y = sin^2(w/2)`` the maxflat half-band product is ``cos^8(w/2) * P(y)``,
``P(y) = 1 + 4y + 10y^2 + 20y^3``.  ``P`` has one real root ``y_r`` and a complex pair ``y_c, conj(y_c)``.
The 9/7 split is ``H(w) ~ cos^4(w/2) (1 - y/y_c)(1 - y/conj(y_c))`` (9 taps, analysis) and
``G(w) ~ cos^4(w/2) (1 - y/y_r)`` (7 taps, synthesis), each normalised to ``sum = sqrt(2)``.
High-pass filters: ``h1[m] = (-1)^(m+1) g[m]`` (analysis), ``g1[m] = (-1)^(m+1) h[m]`` (synthesis).

Subband naming: ``LH`` = low-pass along width, high-pass along height (horizontal edges; PyWavelets' cH),
``HL`` = high-pass along width, low-pass along height (PyWavelets' cV), ``HH`` = high-pass along both.

Example:
    >>> import torch
    >>> x = torch.rand(2, 3, 64, 48)
    >>> ll, highs = dwt2(x, levels=2)
    >>> ll.shape, len(highs), highs[0][0].shape
    (torch.Size([2, 3, 16, 12]), 2, torch.Size([2, 3, 32, 24]))
    >>> torch.allclose(idwt2(ll, highs), x, atol=1e-5)
    True
"""

from __future__ import annotations

import contextlib
import functools

import numpy as np
import torch
import torch.nn.functional as F

__all__ = [
    "WAVELET",
    "MODE",
    "LEVELS",
    "bior44_filters",
    "dwt2",
    "idwt2",
    "ll_subband",
    "pad_to_multiple",
]

WAVELET = "bior4.4"
MODE = "periodization"
LEVELS = 2  #: the decoder reads the LL subband of this level

Highs = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def _poly_in_z_from_y_factor(root: complex) -> np.ndarray:
    """Coefficients (z^-1, z^0, z^1) of ``1 - y/root`` with ``y = (2 - z - 1/z)/4``."""
    c = 1.0 / (4.0 * root)
    return np.array([c, 1.0 - 2.0 * c, c], dtype=complex)


@functools.lru_cache(maxsize=1)
def bior44_filters() -> dict[str, np.ndarray]:
    """The bior4.4 (CDF 9/7) filters derived from their definition, float64, centred and symmetric.

    Returns:
        dict with ``h`` (analysis low-pass, 9 taps, offsets -4..4), ``g`` (synthesis low-pass, 7 taps,
        offsets -3..3), ``h1`` (analysis high-pass, 7 taps, offsets -3..3) and ``g1`` (synthesis
        high-pass, 9 taps, offsets -4..4).
    """
    roots = np.roots([20.0, 10.0, 4.0, 1.0])  # P(y) = 1 + 4y + 10y^2 + 20y^3, highest degree first
    real = [r for r in roots if abs(r.imag) < 1e-12]
    cplx = [r for r in roots if abs(r.imag) >= 1e-12]
    assert len(real) == 1 and len(cplx) == 2
    cos2 = np.array([0.25, 0.5, 0.25])  # cos^2(w/2) = (2 + z + 1/z)/4
    cos4 = np.convolve(cos2, cos2)
    h = np.convolve(cos4, np.convolve(_poly_in_z_from_y_factor(cplx[0]), _poly_in_z_from_y_factor(cplx[1])))
    g = np.convolve(cos4, _poly_in_z_from_y_factor(real[0]))
    h = h.real * (np.sqrt(2.0) / h.real.sum())
    g = g.real * (np.sqrt(2.0) / g.real.sum())
    sign_g = np.array([(-1.0) ** (m + 1) for m in range(-3, 4)])
    sign_h = np.array([(-1.0) ** (m + 1) for m in range(-4, 5)])
    return {"h": h, "g": g, "h1": sign_g * g, "g1": sign_h * h}


@functools.lru_cache(maxsize=16)
def _filters(dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Analysis taps [9, 2] (columns low, high; offsets -4..4) and synthesis polyphase taps [2, 10]
    (rows: output parity 0/1; columns: 5 taps on the low band then 5 on the high band), cached."""
    f = bior44_filters()
    h1 = np.concatenate([[0.0], f["h1"], [0.0]])  # 7 taps -> 9 taps (offsets -4..4)
    g = np.concatenate([[0.0], f["g"], [0.0]])
    g1 = f["g1"]
    ana = np.stack([f["h"], h1], axis=1)
    at = lambda filt, m: filt[m + 4] if -4 <= m <= 4 else 0.0  # noqa: E731
    # x[2p+r] = sum_{t=0..4} lo[p+t-2] g[2(2-t)+r] + hi[p+t-2] g1[2(2-t)+r-1]
    syn = np.array([[at(g, 2 * (2 - t) + r) for t in range(5)] + [at(g1, 2 * (2 - t) + r - 1) for t in range(5)]
                    for r in range(2)])
    return (torch.tensor(ana, dtype=dtype, device=device), torch.tensor(syn.T, dtype=dtype, device=device))


def _wrap_pad(x: torch.Tensor, dim: int, left: int, right: int) -> torch.Tensor:
    """Circular padding of dim ``dim``, valid for any length (also shorter than the pad)."""
    n = x.shape[dim]
    return x.index_select(dim, torch.arange(-left, n + right, device=x.device) % n)


@functools.lru_cache(maxsize=16)
def _bank(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The analysis pair as 10-tap correlation kernels on the wrap-padded signal ``xp[i] = x[i-4]``: row 0
    low-pass (``a[o] = sum_k xp[2o+k] h[k-4]``, taps 0..8), row 1 high-pass (``d[o] = sum_k xp[2o+1+k]
    h1[k-4]``, taps 1..9), [2, 10]."""
    ana, _ = _filters(dtype, device)
    bank = torch.zeros(2, 10, dtype=dtype, device=device)
    bank[0, :9], bank[1, 1:] = ana[:, 0], ana[:, 1]
    return bank


def _exact_fp32() -> contextlib.AbstractContextManager[None]:
    """cuDNN convolutions in IEEE float32 (no TF32: the watermark is a small fraction of the LL values) with
    deterministic algorithms (the same image gives the same subbands and gradients on every run)."""
    from gsw.device import cudnn_flags

    return cudnn_flags(allow_tf32=False, deterministic=True)


class _Correlate(torch.autograd.Function):
    """``conv2d(x, weight, stride, groups)`` with both passes in exact float32 and deterministic (see
    :func:`_exact_fp32`); the filters are constants (no gradient)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, stride: tuple[int, int], groups: int) -> torch.Tensor:
        ctx.save_for_backward(weight)
        ctx.shape, ctx.stride, ctx.groups = x.shape, stride, groups
        with _exact_fp32():
            return F.conv2d(x, weight, stride=stride, groups=groups)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (weight,) = ctx.saved_tensors
        with _exact_fp32():
            gx = torch.nn.grad.conv2d_input(ctx.shape, weight, grad.contiguous(), stride=ctx.stride,
                                            groups=ctx.groups)
        return gx, None, None, None


def _analysis_level(x: torch.Tensor, highs: bool) -> tuple[torch.Tensor, Highs | None]:
    """One 2-D analysis level of ``x`` [..., H, W] (H, W even): ``(LL, (LH, HL, HH))``, or ``(LL, None)``
    when ``highs`` is False (the LL path alone: half the work).

    Two strided correlations over the wrap-padded image: along the width (low and high pass), then along
    the height of each result (grouped).
    """
    lead, (h, w) = x.shape[:-2], x.shape[-2:]
    bank = _bank(x.dtype, x.device)
    rows = bank if highs else bank[:1]
    y = _wrap_pad(x.reshape(-1, 1, h, w), -1, 4, 5)
    y = _Correlate.apply(y, rows.view(-1, 1, 1, 10), (1, 2), 1)  # [N, 1 or 2, H, W/2]: lo_w (, hi_w)
    cols = bank.repeat(2, 1) if highs else bank[:1]
    y = _Correlate.apply(_wrap_pad(y, -2, 4, 5), cols.view(-1, 1, 10, 1), (2, 1), y.shape[1])
    out = y.reshape(*lead, y.shape[1], h // 2, w // 2)  # LL (, LH, HL, HH)
    return out[..., 0, :, :], ((out[..., 1, :, :], out[..., 2, :, :], out[..., 3, :, :]) if highs else None)


def _synthesis_last(lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Inverse of one analysis step along the last dim (:func:`_analysis_level`'s low and high pass):
    x[n] = sum_o lo[o] g[n-2o] + hi[o] g1[n-2o-1] (polyphase)."""
    _, syn = _filters(lo.dtype, lo.device)
    w = torch.cat([_wrap_pad(lo, -1, 2, 2).unfold(-1, 5, 1), _wrap_pad(hi, -1, 2, 2).unfold(-1, 5, 1)], dim=-1)
    out = w @ syn  # [..., N/2, 2]: even and odd samples
    return out.flatten(-2)


def pad_to_multiple(x: torch.Tensor, multiple: int) -> torch.Tensor:
    """Reflect-pad the bottom and right of ``x`` [..., H, W] to multiples of ``multiple``.

    Replicate padding is used where the image is too small for reflection.
    """
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph == 0 and pw == 0:
        return x
    mode = "reflect" if (ph < h and pw < w) else "replicate"
    squeeze = x.dim() == 3
    y = F.pad(x.unsqueeze(0) if squeeze else x, (0, pw, 0, ph), mode=mode)
    return y.squeeze(0) if squeeze else y


def dwt2(x: torch.Tensor, levels: int = LEVELS) -> tuple[torch.Tensor, list[Highs]]:
    """Multi-level 2-D DWT (bior4.4, periodization), differentiable.

    Args:
        x: images [..., H, W] (typically [B, C, H, W]); any float dtype. H and W are reflect-padded
            to multiples of ``2**levels`` first (see module docstring).
        levels: number of decomposition levels (>= 1).

    Returns:
        ``(LL, highs)``: ``LL`` [..., H'/2^levels, W'/2^levels] and ``highs[l]`` = ``(LH, HL, HH)`` of
        level ``l + 1`` (finest first), each [..., H'/2^(l+1), W'/2^(l+1)].
    """
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    if not x.is_floating_point():
        raise TypeError(f"dwt2 expects a floating-point tensor, got {x.dtype}")
    ll = pad_to_multiple(x, 2**levels)
    highs: list[Highs] = []
    for _ in range(levels):
        ll, level = _analysis_level(ll, highs=True)
        highs.append(level)
    return ll, highs


def idwt2(ll: torch.Tensor, highs: list[Highs], size: tuple[int, int] | None = None) -> torch.Tensor:
    """Inverse of :func:`dwt2`.

    Args:
        ll: coarsest approximation [..., h, w].
        highs: ``(LH, HL, HH)`` per level, finest first (as returned by :func:`dwt2`).
        size: optional ``(H, W)`` to crop the (padded) reconstruction back to the original size.

    Returns:
        the reconstructed images [..., H, W].
    """
    x = ll
    for lh, hl, hh in reversed(highs):
        lo_w = _synthesis_last(x.transpose(-1, -2), lh.transpose(-1, -2)).transpose(-1, -2)
        hi_w = _synthesis_last(hl.transpose(-1, -2), hh.transpose(-1, -2)).transpose(-1, -2)
        x = _synthesis_last(lo_w, hi_w)
    if size is not None:
        x = x[..., : size[0], : size[1]]
    return x


def ll_subband(x: torch.Tensor, level: int = LEVELS) -> torch.Tensor:
    """The LL subband of ``level`` (the decoder input), [..., ceil4(H)/4, ceil4(W)/4] for level 2.

    Computed in float32 at least (half-precision inputs are upcast), because the watermark signal is a
    small fraction of the LL values.
    """
    if x.dtype in (torch.float16, torch.bfloat16):
        x = x.float()
    if level < 1:
        raise ValueError(f"level must be >= 1, got {level}")
    if not x.is_floating_point():
        raise TypeError(f"ll_subband expects a floating-point tensor, got {x.dtype}")
    with torch.autocast(device_type=x.device.type, enabled=False):
        ll = pad_to_multiple(x, 2**level)
        for _ in range(level):
            ll, _ = _analysis_level(ll, highs=False)
        return ll
