"""Evaluation of decoders: bit accuracy under attacks, unbiasedness and false positives on unmarked images."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np
import torch

from gsw.data.images import to_unit
from gsw.decoder.dwt import ll_subband
from gsw.decoder.hidden import bit_accuracy
from gsw.attacks.layers import NoiseLayer, draws_per_batch
from gsw.metrics.image import psnr
from gsw.stats import binomial_p_value, false_positive_threshold

__all__ = ["eval_attacks", "eval_attacks_chunked", "unbiasedness", "fair_max_dev", "max_dev_p_value",
           "same_size_groups"]


def same_size_groups(images: Sequence[torch.Tensor], n: int) -> list[list[int]]:
    """Indices of the images in groups of up to ``n`` of one size, each group in the order its images come
    (n = 1: one by one, in order)."""
    groups: list[list[int]] = []
    open_groups: dict[tuple[int, ...], list[int]] = {}
    for i, img in enumerate(images):
        g = open_groups.setdefault(tuple(img.shape), [])
        g.append(i)
        if len(g) == n:
            groups.append(open_groups.pop(tuple(img.shape)))
    return groups + list(open_groups.values())


@torch.no_grad()
def eval_attacks(
    embed_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    decode_fn: Callable[[torch.Tensor], torch.Tensor],
    images: list[torch.Tensor],
    attacks: dict[str, NoiseLayer],
    num_bits: int,
    msgs_per_image: int = 4,
    seed: int = 0,
    device: torch.device | str = "cpu",
    images_per_batch: int = 1,
    per_image: bool = False,
) -> dict[str, object]:
    """Embed random messages into every image (full size), attack, decode.

    Args:
        embed_fn: (imgs [B,3,H,W] in [0,1], msgs [B,k]) -> watermarked imgs.
        decode_fn: LL2 subband -> logits [B,k].
        images: uint8 tensors [3,H,W].
        attacks: name -> noise layer (used at ``strength`` 1; random layers draw from their range, once per
            (image, message) pair, also the layers that draw one strength per batch in training).
        images_per_batch: up to this many images of the same size go through ``embed_fn`` and the attacks
            together (``B = images_per_batch * msgs_per_image``; faster on a GPU, other random draws); 1
            takes the images one by one, in order.
        per_image: also return ``"per_image": {attack: [mean over the image's messages, in image order]}``.

    Returns:
        ``{"bit_acc": {attack: mean}, "bit_acc_std": {...}, "psnr": mean PSNR of watermarked images,
        "n": number of (image, message) pairs}`` (+ ``"per_image"``).
    """
    if images_per_batch < 1:
        raise ValueError(f"images_per_batch must be >= 1, got {images_per_batch}")
    gen = torch.Generator().manual_seed(seed)
    accs: dict[str, list[torch.Tensor]] = {n: [] for n in attacks}
    psnrs, order = [], []
    for group in same_size_groups(images, images_per_batch):
        order += group
        x = torch.cat([(images[i].to(device).float() / 255.0)[None].expand(msgs_per_image, -1, -1, -1)
                       for i in group])
        msgs = torch.cat([torch.randint(0, 2, (msgs_per_image, num_bits), generator=gen) for _ in group])
        msgs = msgs.float().to(device)
        x_w = embed_fn(x, msgs)
        x_w = (x_w.clamp(0, 1) * 255).round() / 255  # a saved 8-bit image
        psnrs.append(psnr(x_w, x).cpu())
        for name, layer in attacks.items():
            layer.strength = 1.0
            if draws_per_batch(layer):  # every pair its own draw (crop size, scale, blur sigma)
                for i in range(x_w.shape[0]):
                    y = layer(x_w[i : i + 1], generator=gen)
                    accs[name].append(bit_accuracy(decode_fn(ll_subband(y)).float(), msgs[i : i + 1]).cpu())
            else:
                y = layer(x_w, generator=gen)
                accs[name].append(bit_accuracy(decode_fn(ll_subband(y)).float(), msgs).cpu())
    out_acc = {n: float(torch.cat(v).mean()) for n, v in accs.items()}
    out_std = {n: float(torch.cat(v).std()) for n, v in accs.items()}
    out = {"bit_acc": out_acc, "bit_acc_std": out_std, "psnr": float(torch.cat(psnrs).mean()),
           "n": len(images) * msgs_per_image}
    if per_image:
        rank = torch.tensor(order).argsort()  # position of each image in the order it was evaluated
        out["per_image"] = {n: torch.cat(v).view(-1, msgs_per_image).mean(1)[rank].tolist() for n, v in accs.items()}
    return out


def eval_attacks_chunked(
    embed_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    decode_fn: Callable[[torch.Tensor], torch.Tensor],
    images: list[torch.Tensor],
    attacks: dict[str, NoiseLayer],
    num_bits: int,
    msgs_per_image: int = 4,
    seed: int = 0,
    device: torch.device | str = "cpu",
    t_end: float = math.inf,
    chunk: int = 10,
) -> dict[str, object]:
    """:func:`eval_attacks` over chunks of ``chunk`` photos (chunk j seeded ``seed + j * chunk``), stopping
    after the first chunk that ends past ``t_end`` (a ``time.perf_counter()`` time).

    Returns:
        ``{"bit_acc", "bit_acc_std", "psnr", "n", "num_images"}`` pooled over the chunks evaluated.
    """
    parts = []
    for i in range(0, len(images), chunk):
        if parts and time.perf_counter() > t_end:
            break
        parts.append(eval_attacks(embed_fn, decode_fn, images[i : i + chunk], attacks, num_bits, msgs_per_image,
                                  seed=seed + i, device=device))
    n = sum(p["n"] for p in parts)
    acc = {a: sum(p["bit_acc"][a] * p["n"] for p in parts) / n for a in attacks}
    var = {a: sum(p["n"] * (p["bit_acc_std"][a] ** 2 + (p["bit_acc"][a] - acc[a]) ** 2) for p in parts) / n
           for a in attacks}
    return {"bit_acc": acc, "bit_acc_std": {a: math.sqrt(v) for a, v in var.items()},
            "psnr": sum(p["psnr"] * p["n"] for p in parts) / n, "n": n, "num_images": n // msgs_per_image}


def _decoded_bits(decode_fn: Callable[[torch.Tensor], torch.Tensor], img: torch.Tensor,
                  device: torch.device | str) -> torch.Tensor:
    """Bits [1,k] (CPU) of one image [3,H,W]: uint8, or float in [0, 1] (e.g. a render)."""
    x = img[None].to(device)
    x = to_unit(x) if x.dtype == torch.uint8 else x.float()  # uint8: as the file reader's float32, bitwise
    return (decode_fn(ll_subband(x)).float() > 0).float().cpu()


@torch.no_grad()
def unbiasedness(
    decode_fn: Callable[[torch.Tensor], torch.Tensor],
    images: list[torch.Tensor],
    num_bits: int,
    num_messages: int = 1000,
    seed: int = 0,
    device: torch.device | str = "cpu",
    extra_views: int = 0,
    fit_images: int | None = None,
) -> dict[str, object]:
    """Decode unmarked images and compare their bits with ``num_messages`` random messages.

    Args:
        decode_fn: LL2 subband -> logits [B,k].
        images: unmarked images [3,H,W], uint8 or float in [0, 1] (decoded at full size).
        extra_views: if > 0, also decode this many random crops (side 0.5..1 of the image, random flips)
            of every image, to estimate the per-bit means with more samples.
        fit_images: number of independent images the whitening's centre was fitted on; adds the floor and
            the p-value of the per-bit deviation for a decoder centred on that many images.

    Returns:
        dict with mean bit accuracy vs the random messages, per-bit P(bit = 1) over images (and its
        max deviation from 0.5), per-bit accuracy vs messages, the false-positive threshold for 1e-6 and the
        number of (image, message) pairs reaching it, the largest number of matching bits seen, and the
        correlation of decoded bits.
    """
    gen = torch.Generator().manual_seed(seed)
    bits = torch.cat([_decoded_bits(decode_fn, img, device) for img in images])  # [N,k]
    msgs = torch.randint(0, 2, (num_messages, num_bits), generator=gen).float()
    matches = bits @ msgs.T + (1 - bits) @ (1 - msgs).T  # [N, M] matching bits
    thr = false_positive_threshold(num_bits)
    per_bit_p1 = bits.mean(0)
    max_dev = float((per_bit_p1 - 0.5).abs().max())
    per_bit_acc = ((bits[:, None, :] == msgs[None]).float().mean((0, 1)))
    n = bits.shape[0]
    corr = torch.corrcoef(bits.T) if n > 2 else torch.zeros(num_bits, num_bits)
    off = corr[~torch.eye(num_bits, dtype=torch.bool)]
    off = off[torch.isfinite(off)]
    res: dict[str, object] = {
        "num_images": n,
        "num_messages": num_messages,
        "mean_bit_acc": float(matches.mean() / num_bits),
        "per_bit_p1": per_bit_p1.tolist(),
        "per_bit_p1_max_dev": max_dev,
        "per_bit_p1_stderr_if_fair": 0.5 / math.sqrt(n),
        "per_bit_p1_max_dev_if_fair": fair_max_dev(n, num_bits),
        "per_bit_p1_max_dev_p_value": max_dev_p_value(max_dev, n, num_bits),
        "per_bit_acc_vs_messages_min": float(per_bit_acc.min()),
        "per_bit_acc_vs_messages_max": float(per_bit_acc.max()),
        "fp_threshold": thr,
        "fp_threshold_prob": binomial_p_value(thr, num_bits) if thr <= num_bits else 0.0,  # k < 20: unreachable
        "false_positives": int((matches >= thr).sum()),
        "max_matching_bits": int(matches.max()),
        "mean_abs_bit_corr": float(off.abs().mean()) if off.numel() else 0.0,
    }
    if fit_images is not None:
        res.update(fit_images=fit_images,
                   per_bit_p1_max_dev_if_fair_fitted=fair_max_dev(n, num_bits, fit_images),
                   per_bit_p1_max_dev_p_value_fitted=max_dev_p_value(max_dev, n, num_bits, fit_images))
    if extra_views > 0:
        vb = []
        for img in images:
            h, w = img.shape[-2:]
            for _ in range(extra_views):
                s = 0.5 + 0.5 * float(torch.rand(1, generator=gen))
                ch, cw = max(16, int(h * s)), max(16, int(w * s))
                y0 = int(torch.randint(0, h - ch + 1, (1,), generator=gen))
                x0 = int(torch.randint(0, w - cw + 1, (1,), generator=gen))
                c = img[:, y0 : y0 + ch, x0 : x0 + cw]
                if float(torch.rand(1, generator=gen)) < 0.5:
                    c = c.flip(-1)
                vb.append(_decoded_bits(decode_fn, c, device))
        vbits = torch.cat(vb)
        p1 = vbits.mean(0)
        res.update(views_num=vbits.shape[0], views_per_bit_p1=p1.tolist(),
                   views_per_bit_p1_max_dev=float((p1 - 0.5).abs().max()),
                   views_per_bit_p1_max_dev_if_fair=fair_max_dev(vbits.shape[0], num_bits),
                   views_mean_bit_acc=float(((vbits @ msgs.T + (1 - vbits) @ (1 - msgs).T) / num_bits).mean()))
    return res


def fair_max_devs(n: int, k: int, n_fit: int | None = None, trials: int = 4000, seed: int = 0) -> np.ndarray:
    """Simulated max_j |P(bit j = 1) - 0.5| over n images of k independent bits of a decoder with no bias.

    Args:
        n: number of evaluation images.
        k: number of bits.
        n_fit: if given, each bit's threshold is the median of ``n_fit`` independent fitting images (what a
            median-centred whitening does) instead of the exact median; the fitting error then adds to the
            evaluation's binomial noise.
        trials: number of simulated evaluations.

    Returns:
        [trials] the max deviation of each simulated evaluation.
    """
    gen = np.random.default_rng(seed)
    p = np.full((trials, k), 0.5)
    if n_fit is not None:  # the CDF value of a sample median of n_fit draws is Beta((n_fit + 1) / 2, ...)
        p = 1.0 - gen.beta((n_fit + 1) / 2, (n_fit + 1) / 2, size=(trials, k))
    return np.abs(gen.binomial(n, p) / n - 0.5).max(1)


def fair_max_dev(n: int, k: int, n_fit: int | None = None, trials: int = 4000, seed: int = 0) -> float:
    """Median of :func:`fair_max_devs`: the worst per-bit deviation an unbiased decoder shows on n images
    (the measurement floor of the per-bit target)."""
    return float(np.median(fair_max_devs(n, k, n_fit, trials, seed)))


def max_dev_p_value(observed: float, n: int, k: int, n_fit: int | None = None, trials: int = 20000) -> float:
    """P(an unbiased decoder shows a max per-bit deviation >= ``observed`` on n images): small values mean
    the measured deviation is more than sampling noise."""
    return float((fair_max_devs(n, k, n_fit, trials, seed=1) >= observed - 1e-12).mean())

