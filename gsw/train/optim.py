"""Adam over named Gaussian parameter tensors, with the optimizer-state surgery densification needs.

Each parameter tensor (``means``, ``sh_dc``, ``sh_rest``, ``opacity_logits``, ``log_scales``, ``quats``) is its
own Adam param group, so it has its own learning rate. When Gaussians are pruned, cloned or split, the
parameters are replaced by new leaf tensors and Adam's ``exp_avg`` / ``exp_avg_sq`` rows are carried along:
pruned rows are dropped, appended rows start at zero (as in the INRIA code), and the per-group ``step`` count
is kept.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["GaussianAdam"]


class GaussianAdam:
    """Adam with per-tensor learning rates and row-wise state surgery.

    Args:
        params: name -> leaf tensor (first dimension ``N``, shared by all).
        lrs: name -> learning rate.
        eps: Adam epsilon (INRIA: 1e-15).
    """

    def __init__(self, params: dict[str, Tensor], lrs: dict[str, float], eps: float = 1e-15) -> None:
        self.params = {k: v.detach().clone().requires_grad_(True) for k, v in params.items()}
        self.optimizer = torch.optim.Adam(
            [{"params": [p], "lr": float(lrs[k]), "name": k} for k, p in self.params.items()], lr=0.0, eps=eps)

    # ------------------------------------------------------------------ plain optimiser API
    def zero_grad(self) -> None:
        """Drop gradients."""
        self.optimizer.zero_grad(set_to_none=True)

    def step(self) -> None:
        """One Adam step."""
        self.optimizer.step()

    def set_lr(self, name: str, lr: float) -> None:
        """Set one group's learning rate."""
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                group["lr"] = float(lr)

    def lr(self, name: str) -> float:
        """One group's learning rate."""
        return next(float(g["lr"]) for g in self.optimizer.param_groups if g["name"] == name)

    # ------------------------------------------------------------------ surgery
    def _swap(self, name: str, new: Tensor, state_fn) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] != name:
                continue
            old = group["params"][0]
            state = self.optimizer.state.pop(old, None)
            param = new.detach().requires_grad_(True)
            group["params"][0] = param
            if state:
                state = dict(state)
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in state:
                        state[key] = state_fn(state[key])
                self.optimizer.state[param] = state
            self.params[name] = param
            return
        raise KeyError(name)

    def prune(self, keep: Tensor) -> None:
        """Keep only the rows where the bool mask ``keep [N]`` is true (parameters and Adam moments)."""
        for name in list(self.params):
            self._swap(name, self.params[name].detach()[keep], lambda s: s[keep])

    def append(self, extra: dict[str, Tensor]) -> None:
        """Append rows (``extra[name]`` has the same trailing shape); their Adam moments start at zero."""
        for name in list(self.params):
            rows = extra[name].to(self.params[name])
            self._swap(name, torch.cat([self.params[name].detach(), rows]),
                       lambda s, rows=rows: torch.cat([s, torch.zeros_like(rows)]))

    def replace(self, name: str, value: Tensor) -> None:
        """Replace one tensor (same shape) and zero its Adam moments (INRIA's opacity reset)."""
        self._swap(name, value, torch.zeros_like)
