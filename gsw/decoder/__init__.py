"""The frozen watermark decoders: bior4.4 DWT, HiDDeN networks, whitening, the shipped weights.

Torch-only: this subpackage never loads the compiled rasterizer. Their pre-training lives in
:mod:`gsw.decoder.pretrain` (``gsw decoder train|export``).

Public API:
    - DWT (the project's single wavelet transform): :func:`dwt2`, :func:`idwt2`, :func:`ll_subband`.
    - Networks: :class:`HiddenEncoder`, :class:`HiddenDecoder`, :class:`WhiteningLayer`, :func:`fit_whitening`.
    - Shipped decoders: :func:`load_decoder` -> :class:`WatermarkDecoder` (32/48/64 bits, sha256-checked),
      :func:`save_decoder`, :class:`WeightsError`.
    - Readouts: :class:`KleinReadout` (flip-antisymmetric: cancels a decoder's per-bit lean; opt-in).

Example:
    >>> import torch
    >>> from gsw.decoder import load_decoder, ll_subband
    >>> dec = load_decoder(48)
    >>> dec(ll_subband(torch.rand(2, 3, 128, 128))).shape
    torch.Size([2, 48])
"""

from gsw.decoder.dwt import LEVELS, MODE, WAVELET, dwt2, idwt2, ll_subband
from gsw.decoder.readout import KleinReadout
from gsw.decoder.hidden import HiddenDecoder, HiddenEncoder, bit_accuracy, bits_from_logits
from gsw.decoder.whitening import WhiteningLayer, fit_whitening
from gsw.decoder.zoo import AVAILABLE_BITS, WatermarkDecoder, WeightsError, load_decoder, save_decoder

__all__ = [
    "AVAILABLE_BITS", "LEVELS", "MODE", "WAVELET", "HiddenDecoder", "HiddenEncoder", "KleinReadout",
    "WatermarkDecoder", "WeightsError", "WhiteningLayer", "bit_accuracy", "bits_from_logits", "dwt2", "fit_whitening",
    "idwt2", "ll_subband", "load_decoder", "save_decoder",
]
