"""Image quality metrics: PSNR and SSIM (kornia's Gaussian-window SSIM).

Images are float tensors in ``[0, data_range]``, ``[3, H, W]`` or batched ``[B, 3, H, W]``.

SSIM conventions: 11x11 Gaussian window (sigma 1.5), ``c1 = (0.01 L)^2``, ``c2 = (0.03 L)^2``, ``'same'``
(reflect) padding, mean over pixels and channels — the INRIA 3DGS metric up to the border treatment (INRIA pads
with zeros). :func:`ssim_loss` is INRIA's ``1 - SSIM`` (not ``(1 - SSIM) / 2``).

Example:
    >>> import torch
    >>> from gsw.metrics import psnr, ssim
    >>> a = torch.rand(3, 32, 32)
    >>> round(float(ssim(a, a)), 4), float(psnr(a, a)) == float("inf")
    (1.0, True)
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["psnr", "ssim", "ssim_loss", "mse"]


def _batched(img: Tensor, ref: Tensor) -> tuple[Tensor, Tensor]:
    if img.shape != ref.shape:
        raise ValueError(f"image shapes differ: {list(img.shape)} vs {list(ref.shape)}")
    if img.dim() == 3:
        return img[None], ref[None]
    if img.dim() != 4:
        raise ValueError(f"expected [C, H, W] or [B, C, H, W], got {list(img.shape)}")
    return img, ref


def mse(img: Tensor, ref: Tensor) -> Tensor:
    """Mean squared error per image: ``[B]`` (or a scalar for unbatched ``[C, H, W]`` input)."""
    a, b = _batched(img, ref)
    out = (a - b).pow(2).flatten(1).mean(1)
    return out[0] if img.dim() == 3 else out


def psnr(img: Tensor, ref: Tensor, data_range: float = 1.0) -> Tensor:
    """Peak signal-to-noise ratio in dB, per image: ``-10 log10(mse / data_range^2)``.

    The one PSNR of the package (embedding, decoder evaluation, reports). Identical images give ``inf`` (no
    clamping of the MSE). Computed in the inputs' dtype.

    Args:
        img: ``[C, H, W]`` or ``[B, C, H, W]``.
        ref: same shape.
        data_range: ``L``, the peak value.

    Returns:
        ``[B]`` (one PSNR per image; average them for a dataset score, as INRIA does) or a scalar for unbatched
        input.
    """
    return -10.0 * torch.log10(mse(img, ref) / data_range**2)


def ssim(img: Tensor, ref: Tensor, *, window_size: int = 11, data_range: float = 1.0,
         reduce: bool = True) -> Tensor:
    """Structural similarity (kornia's map, Gaussian window), mean per image (``[B]`` or scalar).

    Args:
        img: ``[C, H, W]`` or ``[B, C, H, W]``.
        ref: same shape.
        window_size: odd Gaussian window size (sigma 1.5).
        data_range: ``L``.
        reduce: return the per-image mean (else the ``[B, C, H, W]`` map).
    """
    import kornia  # noqa: PLC0415 - kept lazy: kornia import costs ~1 s

    a, b = _batched(img, ref)
    smap = kornia.metrics.ssim(a, b, window_size, max_val=float(data_range))
    if not reduce:
        return smap
    out = smap.flatten(1).mean(1)
    return out[0] if img.dim() == 3 else out


def ssim_loss(img: Tensor, ref: Tensor, *, window_size: int = 11) -> Tensor:
    """INRIA's D-SSIM term ``1 - SSIM`` (scalar, mean over the batch); differentiable."""
    return 1.0 - ssim(img, ref, window_size=window_size).mean()
