"""The 3D-GSW fine-tuning objective.

`L = w_l1 * L1(I_w, I_o) + w_lpips * LPIPS(I_w, I_o) + w_sub * sum_{l=1,2} sum_{S in LH,HL,HH} L1(S_l, S_l^o)
 + w_msg * BCE(D(LL_2(I_w)), M)` with defaults 1, 0.2, 0.3, 0.15 (paper: 0.4 for the message term), where `I_o` is the render of
the original model, `S_l` the wavelet subbands of the project's DWT (:mod:`gsw.decoder.dwt`) and `D`
the frozen decoder (logits; bit = logit > 0).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch.nn.functional as F
from torch import Tensor, nn

from gsw.decoder.dwt import LEVELS, dwt2, ll_subband


@dataclass(frozen=True)
class LossWeights:
    """Weights of the four loss terms (paper defaults)."""

    l1: float = 1.0
    lpips: float = 0.2
    subband: float = 0.3
    message: float = 0.15  # paper: 0.4 (BENCHMARKS.md §6a: the weight that keeps >= 35 dB)


def lpips_weights(net: str | None, weights: LossWeights | None = None) -> LossWeights:
    """The loss weights that go with the LPIPS network ``net``: the rule "LPIPS off => its weight 0".

    Args:
        net: "vgg" or "alex", or None for no LPIPS term.
        weights: the weights with the term on (default: :class:`LossWeights`).

    Returns:
        ``weights``, with ``lpips = 0`` when ``net`` is None.
    """
    weights = LossWeights() if weights is None else weights
    return weights if net is not None else replace(weights, lpips=0.0)


def subband_l1(image: Tensor, target: Tensor, levels: int = LEVELS) -> Tensor:
    """Sum over levels 1..`levels` and LH/HL/HH of the mean absolute subband difference.

    Args:
        image: [B, 3, H, W] or [3, H, W].
        target: same shape.
    """
    _, highs = dwt2(image, levels)
    _, highs_t = dwt2(target, levels)
    return sum((a - b).abs().mean() for level, level_t in zip(highs, highs_t)
               for a, b in zip(level, level_t))


def message_loss(logits: Tensor, message: Tensor, logit_scale: float = 1.0) -> Tensor:
    """Binary cross-entropy of `logit_scale` * decoder logits [B, k] against the message bits [k] or [B, k].

    A large scale (the official code uses 10) saturates the loss of bits that are already right, so the
    gradient concentrates on the wrong ones (a soft hinge) instead of pushing every bit further.
    """
    return F.binary_cross_entropy_with_logits(logits * logit_scale, message.to(logits).expand_as(logits))


class WatermarkLoss(nn.Module):
    """The full objective for one view.

    Args:
        decoder: frozen decoder mapping LL2 subbands [B, 3, h, w] to logits [B, k]
            (:class:`gsw.decoder.WatermarkDecoder`).
        weights: the loss weights.
        lpips_net: "vgg" or "alex" (real pretrained LPIPS weights, see :mod:`gsw.metrics.lpips`);
            None disables the LPIPS term (its weight must then be 0).
        logit_scale: factor on the logits inside the message BCE (see :func:`message_loss`).
    """

    def __init__(self, decoder: nn.Module, weights: LossWeights = LossWeights(),
                 lpips_net: str | None = "vgg", logit_scale: float = 1.0) -> None:
        super().__init__()
        if not logit_scale > 0:
            raise ValueError(f"logit_scale must be > 0, got {logit_scale}")
        self.decoder = decoder.eval().requires_grad_(False)
        self.weights = weights
        self.logit_scale = float(logit_scale)
        if weights != lpips_weights(lpips_net, weights):
            raise ValueError("LPIPS is disabled but its weight is not 0")
        if lpips_net is None:
            self.lpips = None
        else:
            from gsw.metrics.lpips import LPIPS

            self.lpips = LPIPS(net=lpips_net)

    def forward(self, render: Tensor, original: Tensor, message: Tensor,
                decoder_input: Tensor | None = None) -> tuple[Tensor, dict[str, float], Tensor]:
        """Loss of a watermarked render against the original render.

        Args:
            render: [3, H, W] watermarked render in [0, 1] (differentiable).
            original: [3, H, W] render of the original model.
            message: [k] bits.
            decoder_input: optional [3, H', W'] image to decode instead of `render` (an attacked
                copy for train-time attack sampling).

        Returns:
            (total loss, {term: value}, decoder logits [k]).
        """
        w = self.weights
        x, y = render.unsqueeze(0), original.unsqueeze(0)
        decoded = x if decoder_input is None else decoder_input.unsqueeze(0)
        logits = self.decoder(ll_subband(decoded))
        terms = {"l1": (x - y).abs().mean(), "subband": subband_l1(x, y),
                 "message": message_loss(logits, message, self.logit_scale)}
        if self.lpips is not None:
            terms["lpips"] = self.lpips(x, y).mean()
        total = (w.l1 * terms["l1"] + w.subband * terms["subband"] + w.message * terms["message"]
                 + (w.lpips * terms["lpips"] if "lpips" in terms else 0.0))
        return total, {k: float(v.detach()) for k, v in terms.items()}, logits[0]
