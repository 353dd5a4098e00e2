"""Watermark decoder: bior4.4 DWT, HiDDeN encoder/decoder, noise layers, whitening (PCA or ZCA), shipped weights.

This subpackage imports nothing from the rest of ``gsw`` (no compiled extension), so it also runs where
the extension is not built.

Public API:
    - DWT (the project's single wavelet transform): :func:`dwt2`, :func:`idwt2`, :func:`ll_subband`.
    - Networks: :class:`HiddenEncoder`, :class:`HiddenDecoder`, :class:`WhiteningLayer`, :func:`fit_whitening`.
    - Shipped decoders: :func:`load_decoder` -> :class:`WatermarkDecoder` (32/48/64 bits, sha256-checked),
      :func:`save_decoder`, :class:`WeightsError`.
    - Noise layers: :mod:`gsw.watermark.noise`.
    - Image-space embedding against a frozen decoder: :func:`watermark_images` (:mod:`gsw.watermark.image`),
      built on :func:`refine_residual` (:mod:`gsw.watermark.refine`).
    - Metrics: :func:`bit_accuracy`, :func:`false_positive_threshold`.

Example:
    >>> import torch
    >>> from gsw.watermark import load_decoder, ll_subband
    >>> dec = load_decoder(48)
    >>> dec(ll_subband(torch.rand(2, 3, 128, 128))).shape
    torch.Size([2, 48])
"""

from .dwt import LEVELS, MODE, WAVELET, dwt2, idwt2, ll_subband
from .evaluation import false_positive_threshold
from .hidden import HiddenDecoder, HiddenEncoder, bit_accuracy, bits_from_logits
from .image import watermark_images
from .refine import refine_residual
from .whitening import WhiteningLayer, fit_whitening
from .zoo import AVAILABLE_BITS, WatermarkDecoder, WeightsError, load_decoder, save_decoder

__all__ = [
    "AVAILABLE_BITS",
    "LEVELS",
    "MODE",
    "WAVELET",
    "HiddenDecoder",
    "HiddenEncoder",
    "WatermarkDecoder",
    "WeightsError",
    "WhiteningLayer",
    "bit_accuracy",
    "bits_from_logits",
    "dwt2",
    "false_positive_threshold",
    "fit_whitening",
    "idwt2",
    "ll_subband",
    "load_decoder",
    "refine_residual",
    "save_decoder",
    "watermark_images",
]
