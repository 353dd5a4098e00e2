"""Whitening of pre-trained decoders on unmarked photos (ZCA, median-centred: the shipped recipe)."""

from __future__ import annotations

import torch

from gsw.decoder.dwt import ll_subband
from gsw.decoder.hidden import HiddenDecoder
from gsw.decoder.pretrain.config import UNMARKED_CROP_SIZES, WHITEN_EIG_FLOOR
from gsw.decoder.pretrain.data import bank_crops
from gsw.decoder.whitening import WhiteningLayer
from gsw.decoder.zoo import load_decoder

__all__ = ["fit_whitening_multi", "shipped_whitening"]


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
    """Whitening of each (eval-mode) decoder on the same unmarked inputs.

    The inputs are every full photo of ``images`` (uint8 [3,H,W]) and its mirror image, plus ``num_crops``
    random crops (+ flips) of ``bank`` in ``crop_sizes`` (capped at the bank's height and width). ``mode`` /
    ``center`` / ``eps`` as in :meth:`WhiteningLayer.fit`; the default ``eps`` (relative to the largest
    eigenvalue) caps the gain at ~30x the top direction's: a decoder trained with the balance loss can have a
    dead output direction (eigenvalue ~1e-11) that an unregularised inverse square root would amplify by ~1e5,
    turning float rounding (TF32 on GPUs) into bit flips.

    Returns:
        the layers (on the CPU) and the number of samples they were fitted on.
    """
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
        s = min(s, *bank.shape[-2:])  # photos smaller than a crop size: whole-bank crops
        for i0 in range(0, per, 250):
            ll = ll_subband(bank_crops(bank, min(250, per - i0), s, gen))
            for i, d in enumerate(decoders):
                outs[i].append(d(ll).float().cpu())
    layers = [WhiteningLayer(d.num_bits).fit(torch.cat(o), mode=mode, center=center, eps=eps)
              for d, o in zip(decoders, outs)]
    return layers, int(torch.cat(outs[0]).shape[0])


def shipped_whitening(decoder: HiddenDecoder, num_bits: int) -> WhiteningLayer:
    """The package's whitening for ``num_bits`` bits, after checking that ``decoder`` is the shipped decoder.

    Raises:
        ValueError: ``decoder``'s weights differ from the shipped decoder's.
    """
    shipped = load_decoder(num_bits)
    ours = {n: v.detach().cpu() for n, v in decoder.state_dict().items()}
    if any(not torch.equal(ours[n], v) for n, v in shipped.decoder.state_dict().items()):
        raise ValueError(f"the {num_bits}-bit decoder is not the shipped one: the shipped whitening does not apply")
    return shipped.whitening
