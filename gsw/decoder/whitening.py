"""PCA whitening of decoder outputs (the Stable Signature recipe).

After pre-training, the decoder's raw outputs on *unmarked* images are biased and correlated, so an
unmarked image would match some messages far more often than chance.  :func:`fit_whitening` measures the
mean ``mu`` and covariance ``S`` of the outputs over a set of unmarked images, takes the
eigendecomposition ``S = V diag(lam) V^T`` and builds the fixed affine map

    ``y = W (x - mu)`` with ``W = diag(lam + eps)^(-1/2) V^T``  (PCA)  or ``V diag(lam + eps)^(-1/2) V^T`` (ZCA),

so that on the fitting set the whitened outputs have zero mean and identity covariance: each bit
(``y > 0``) is centred and the bits are decorrelated.  The layer is frozen (buffers, no parameters).

ZCA is the whitening closest to the identity: it decorrelates while keeping every output on its own bit
axis, so a decoder trained with a message encoder still reads that encoder's bits after whitening (PCA
rotates the axes and a PCA-whitened bit is a mix of all raw bits).  ``center="median"`` shifts the
whitened outputs so that each bit is 1 on exactly half of the fitting set; the mean of heavy-tailed
outputs leaves most images on one side of zero.

Example:
    >>> import torch
    >>> x = torch.randn(500, 8) @ torch.randn(8, 8) + 3.0
    >>> layer = WhiteningLayer.from_outputs(x)
    >>> y = layer(x)
    >>> bool(y.mean(0).abs().max() < 1e-4), bool((y.T @ y / 499 - torch.eye(8)).abs().max() < 1e-3)
    (True, True)
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import torch
from torch import nn

__all__ = ["WhiteningLayer", "fit_whitening"]


class WhiteningLayer(nn.Module):
    """Fixed affine map ``y = x @ weight.T + bias`` (no trainable parameters).

    Args:
        num_bits: dimension k.
    """

    weight: torch.Tensor
    bias: torch.Tensor

    def __init__(self, num_bits: int) -> None:
        super().__init__()
        self.num_bits = num_bits
        self.register_buffer("weight", torch.eye(num_bits))
        self.register_buffer("bias", torch.zeros(num_bits))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [..., k] -> whitened [..., k]."""
        return torch.nn.functional.linear(x, self.weight.to(x.dtype), self.bias.to(x.dtype))

    @torch.no_grad()
    def fit(self, outputs: torch.Tensor, mode: str = "pca", eps: float = 1e-12,
            center: str = "mean") -> "WhiteningLayer":
        """Fit to decoder outputs [N, k] of unmarked images (float64 internally).

        Args:
            outputs: raw decoder outputs, N > k rows.
            mode: ``"pca"`` (``W = lam^-1/2 V^T``, Stable Signature) or ``"zca"`` (``V lam^-1/2 V^T``).
            eps: added to the eigenvalues (relative to the largest) before the inverse square root.
            center: ``"mean"`` (whitened outputs have zero mean) or ``"median"`` (zero median per bit).
        """
        if center not in ("mean", "median"):
            raise ValueError(f"center must be 'mean' or 'median', got {center!r}")
        if outputs.dim() != 2 or outputs.shape[1] != self.num_bits:
            raise ValueError(f"outputs must be [N, {self.num_bits}], got {tuple(outputs.shape)}")
        n = outputs.shape[0]
        if n <= self.num_bits:
            raise ValueError(f"need more than {self.num_bits} samples to fit, got {n}")
        x = outputs.detach().double()
        mu = x.mean(dim=0)
        xc = x - mu
        cov = xc.T @ xc / (n - 1)
        lam, v = torch.linalg.eigh(cov)
        lam = lam.clamp_min(0) + eps * lam.max().clamp_min(1e-30)
        w = torch.diag(lam.rsqrt()) @ v.T
        if mode == "zca":
            w = v @ w
        elif mode != "pca":
            raise ValueError(f"mode must be 'pca' or 'zca', got {mode!r}")
        bias = -(w @ mu)
        if center == "median":
            bias = bias - (xc @ w.T).median(dim=0).values
        self.weight.copy_(w.to(self.weight.dtype))
        self.bias.copy_(bias.to(self.bias.dtype))
        return self

    @classmethod
    def from_outputs(cls, outputs: torch.Tensor, mode: str = "pca", center: str = "mean") -> "WhiteningLayer":
        """Build and fit a layer from decoder outputs [N, k]."""
        return cls(outputs.shape[1]).fit(outputs, mode=mode, center=center)


@torch.no_grad()
def fit_whitening(
    decoder: Callable[[torch.Tensor], torch.Tensor],
    batches: Iterable[torch.Tensor],
    num_bits: int,
    mode: str = "pca",
    center: str = "mean",
) -> tuple[WhiteningLayer, torch.Tensor]:
    """Run ``decoder`` (in eval mode) over batches of decoder inputs (LL2 subbands of unmarked images).

    Returns:
        the fitted :class:`WhiteningLayer` (on the CPU) and the raw outputs [N, k] (float32, CPU).
    """
    was_training = getattr(decoder, "training", False)
    if hasattr(decoder, "eval"):
        decoder.eval()
    outs = [decoder(b).float().cpu() for b in batches]
    if was_training and hasattr(decoder, "train"):
        decoder.train()
    raw = torch.cat(outs)
    return WhiteningLayer(num_bits).fit(raw, mode=mode, center=center), raw
