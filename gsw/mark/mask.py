"""The 3D-GSW gradient mask, applied to the optimiser's *update* so that it actually works with Adam.

The paper weights each parameter element by `w = exp(-|theta|^beta)` (beta = 4), normalised per
parameter tensor, so that elements of large magnitude change less. The official code multiplies
the normalised weights into `.grad` before `Adam.step()`; Adam divides by the running RMS of the
gradient, so a fixed per-element factor cancels (the mask degenerates to an on/off gate).
Here the mask scales the step Adam takes: `theta <- theta + m * (adam_step(theta) - theta)` with
`m = w / max(w)` in [0, 1] (the per-tensor normalisation by the maximum keeps the step of the
least-protected element unchanged). The weights are formed in float64 in log space relative to
the tensor's smallest |theta|; as in the paper, elements whose |theta|^beta exceeds the smallest
by more than ~87 get a float32 mask of 0 (they are frozen).

`kind="stega"` is the StegaNeRF-style magnitude mask without the exponential,
`w = 1 / (|theta| + eps)^beta`, also normalised by its maximum.
"""

from __future__ import annotations

from typing import Iterable

import torch
from torch import Tensor

#: Exponent of the paper's mask.
BETA = 4.0


def exp_mask(param: Tensor, beta: float = BETA) -> Tensor:
    """`exp(-|theta|^beta)` normalised by its maximum over the tensor; same shape as `param`."""
    e = param.detach().double().abs().pow(beta)
    return torch.exp(-(e - e.min())).to(param.dtype) if e.numel() else e.to(param.dtype)


def stega_mask(param: Tensor, beta: float = 1.0, eps: float = 1e-3) -> Tensor:
    """StegaNeRF-style `1 / (|theta| + eps)^beta` normalised by its maximum; same shape."""
    logw = -beta * torch.log(param.detach().double().abs() + eps)
    return torch.exp(logw - logw.max()).to(param.dtype) if logw.numel() else logw.to(param.dtype)


class UpdateMask:
    """Scales each optimiser step element-wise by a fixed mask computed once from the initial values.

    Args:
        params: the parameter tensors to protect (leaf tensors optimised by `optimizer`).
        kind: "exp" (3D-GSW), "stega" (StegaNeRF) or "none".
        beta: exponent (defaults: 4 for "exp", 1 for "stega").

    Example:
        >>> p = torch.tensor([0.1, 2.0], requires_grad=True)
        >>> opt = torch.optim.Adam([p], lr=0.1)
        >>> mask = UpdateMask([p])
        >>> p.sum().backward(); mask.step(opt)
        >>> bool((p.detach() - torch.tensor([0.1, 2.0])).abs().argmax() == 0)
        True
    """

    def __init__(self, params: Iterable[Tensor], kind: str = "exp", beta: float | None = None) -> None:
        if kind not in ("exp", "stega", "none"):
            raise ValueError(f"mask kind must be 'exp', 'stega' or 'none', got {kind!r}")
        self.kind = kind
        self.params = list(params)
        if kind == "exp":
            self.masks = [exp_mask(p, BETA if beta is None else beta) for p in self.params]
        elif kind == "stega":
            self.masks = [stega_mask(p, 1.0 if beta is None else beta) for p in self.params]
        else:
            self.masks = [None for _ in self.params]

    @torch.no_grad()
    def step(self, optimizer: torch.optim.Optimizer) -> None:
        """Runs `optimizer.step()` and keeps only the masked share of each parameter's change."""
        if self.kind == "none":
            optimizer.step()
            return
        before = [p.detach().clone() for p in self.params]
        optimizer.step()
        for p, old, m in zip(self.params, before, self.masks):
            p.copy_(old + m * (p - old))
