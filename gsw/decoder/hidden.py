"""HiDDeN encoder and decoder (Zhu et al. 2018; decoder as in Stable Signature / 3D-GSW).

* :class:`HiddenEncoder` embeds a k-bit message into an RGB image (values in [0, 1]) and returns a
  residual of the image's size: Conv-BN-ReLU blocks on the image, the message broadcast to an H x W x k
  map and concatenated with the features and the image, one more block, a 1x1 conv to 3 channels.
* :class:`HiddenDecoder` reads a k-bit message from the **level-2 LL subband** of an image
  (:func:`gsw.decoder.dwt.ll_subband`, raw values, no resize or normalisation):
  8 Conv3x3-BN-GELU blocks of 64 channels, a 64->k Conv3x3-BN-GELU block, global average pooling and a
  k x k linear layer.  It returns logits: a bit is 1 where the logit is > 0.

Example:
    >>> import torch
    >>> from gsw.decoder.dwt import ll_subband
    >>> enc, dec = HiddenEncoder(32), HiddenDecoder(32)
    >>> img, msg = torch.rand(2, 3, 64, 64), torch.randint(0, 2, (2, 32)).float()
    >>> dec(ll_subband(img + enc(img, msg))).shape
    torch.Size([2, 32])
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["ConvBNAct", "HiddenEncoder", "HiddenDecoder", "bits_from_logits", "fold_batchnorm", "bit_accuracy",
           "scale_to_psnr"]


class ConvBNAct(nn.Sequential):
    """Conv3x3 (stride 1, padding 1) -> BatchNorm -> activation."""

    def __init__(self, cin: int, cout: int, act: str = "gelu") -> None:
        acts = {"gelu": nn.GELU, "relu": nn.ReLU}
        super().__init__(nn.Conv2d(cin, cout, 3, 1, 1), nn.BatchNorm2d(cout, eps=1e-3), acts[act]())


class HiddenEncoder(nn.Module):
    """HiDDeN encoder: image [B,3,H,W] in [0,1] and message [B,k] in {0,1} -> residual [B,3,H,W].

    The residual is unscaled; the caller sets its strength (:func:`scale_to_psnr` normalises it to a
    target PSNR).
    """

    def __init__(self, num_bits: int, num_blocks: int = 4, channels: int = 64) -> None:
        super().__init__()
        self.num_bits = num_bits
        blocks = [ConvBNAct(3, channels, "relu")]
        blocks += [ConvBNAct(channels, channels, "relu") for _ in range(num_blocks - 1)]
        self.features = nn.Sequential(*blocks)
        self.after_concat = ConvBNAct(channels + 3 + num_bits, channels, "relu")
        self.final = nn.Conv2d(channels, 3, kernel_size=1)

    def forward(self, imgs: torch.Tensor, msgs: torch.Tensor) -> torch.Tensor:
        """imgs [B,3,H,W] in [0,1], msgs [B,k] in {0,1} -> residual [B,3,H,W]."""
        x = imgs * 2.0 - 1.0
        feats = self.features(x)
        m = (msgs.to(x.dtype) * 2.0 - 1.0)[:, :, None, None].expand(-1, -1, x.shape[-2], x.shape[-1])
        feats = self.after_concat(torch.cat([feats, x, m], dim=1))
        return self.final(feats)


class HiddenDecoder(nn.Module):
    """HiDDeN decoder on the LL2 subband: [B,3,h,w] -> logits [B,k] (bit = logit > 0).

    Args:
        num_bits: message length k.
        num_blocks: number of 64-channel Conv3x3-BN-GELU blocks (8 as in Stable Signature).
        channels: width of the blocks.
        input_norm: ``"none"`` (default) feeds LL2 raw, as the official code; ``"center"`` subtracts
            each image's per-channel mean; ``"standardize"`` also divides by the image's RMS after
            centring, which makes the decoder invariant to brightness offsets and contrast gains.  Raw
            LL2 values sit around 2, and that brightness dominates the first layers and the batch
            statistics: against fixed on/off templates (4 bits, 22 dB) a raw decoder stayed at chance
            for 300 steps where a centred one reached 82 % (BENCHMARKS.md, section 5).
    """

    NORMS = ("none", "center", "standardize")

    def __init__(self, num_bits: int, num_blocks: int = 8, channels: int = 64,
                 input_norm: str = "none") -> None:
        super().__init__()
        if input_norm not in self.NORMS:
            raise ValueError(f"input_norm must be one of {self.NORMS}, got {input_norm!r}")
        self.num_bits = num_bits
        self.input_norm = input_norm
        layers = [ConvBNAct(3, channels)] + [ConvBNAct(channels, channels) for _ in range(num_blocks - 1)]
        layers.append(ConvBNAct(channels, num_bits))
        self.layers = nn.Sequential(*layers)
        self.pool = nn.AdaptiveAvgPool2d((1, 1))
        self.linear = nn.Linear(num_bits, num_bits)

    def forward(self, ll: torch.Tensor) -> torch.Tensor:
        """ll [B,3,h,w] (level-2 LL subband of images in [0,1]) -> logits [B,k]."""
        if self.input_norm != "none":
            ll = ll - ll.mean(dim=(2, 3), keepdim=True)
            if self.input_norm == "standardize":
                ll = ll * torch.rsqrt(ll.pow(2).mean(dim=(1, 2, 3), keepdim=True) + 1e-4)
        x = self.pool(self.layers(ll)).flatten(1)
        return self.linear(x)


def fold_batchnorm(module: nn.Module) -> nn.Module:
    """A copy of a frozen network with every ``Conv2d`` -> ``BatchNorm2d`` pair of its ``nn.Sequential`` blocks
    folded into one convolution (the BatchNorm becomes an identity): the same function in eval mode, one kernel
    and one backward pass fewer per block. ``module`` itself is left as it is.

    Args:
        module: a network in eval mode (the running statistics are folded, not the batch statistics).

    Raises:
        ValueError: ``module`` is in training mode.
    """
    import copy

    from torch.nn.utils.fusion import fuse_conv_bn_eval

    if module.training:
        raise ValueError("fold_batchnorm needs a network in eval mode (it folds the running statistics)")
    out = copy.deepcopy(module)
    for seq in [m for m in out.modules() if isinstance(m, nn.Sequential)]:
        names = list(seq._modules)
        for a, b in zip(names, names[1:]):
            conv, bn = seq._modules[a], seq._modules[b]
            if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d) and bn.track_running_stats:
                seq._modules[a] = fuse_conv_bn_eval(conv, bn).requires_grad_(conv.weight.requires_grad)
                seq._modules[b] = nn.Identity()
    return out


def bits_from_logits(logits: torch.Tensor) -> torch.Tensor:
    """logits [..., k] -> bits [..., k] in {0, 1} (float): 1 where logit > 0."""
    return (logits > 0).to(logits.dtype if logits.is_floating_point() else torch.float32)


def bit_accuracy(logits: torch.Tensor, msgs: torch.Tensor) -> torch.Tensor:
    """Per-sample fraction of correctly decoded bits: logits [B,k], msgs [B,k] in {0,1} -> [B]."""
    return ((logits > 0) == (msgs > 0.5)).float().mean(dim=-1)


def scale_to_psnr(residual: torch.Tensor, psnr: float) -> torch.Tensor:
    """residual [B,3,H,W] rescaled per image to the RMS of ``psnr`` dB (images in [0, 1])."""
    rms = residual.pow(2).mean(dim=(1, 2, 3), keepdim=True).add(1e-12).sqrt()
    return residual * (10.0 ** (-psnr / 20.0) / rms)
