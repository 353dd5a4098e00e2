"""The optimisation state of a training run: parameters, Adam, and INRIA's adaptive density control
(clone / split / prune, opacity reset; see :mod:`gsw.train`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.gaussians import quat_to_rotmat, Gaussians
from gsw.train.config import TrainConfig
from gsw.train.optim import GaussianAdam


def _position_lr(step: int, cfg: TrainConfig, extent: float) -> float:
    """INRIA's ``get_expon_lr_func``: log-linear decay with an optional delayed warm-up."""
    max_steps = cfg.position_lr_max_steps or cfg.iterations
    lr_init, lr_final = cfg.position_lr_init * extent, cfg.position_lr_final * extent
    if step < 0 or (lr_init == 0.0 and lr_final == 0.0):
        return 0.0
    if cfg.position_lr_delay_steps > 0:
        delay = cfg.position_lr_delay_mult + (1 - cfg.position_lr_delay_mult) * math.sin(
            0.5 * math.pi * min(max(step / cfg.position_lr_delay_steps, 0.0), 1.0))
    else:
        delay = 1.0
    t = min(max(step / max_steps, 0.0), 1.0)
    return delay * math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)


class _State:
    """Parameters, optimiser and densification statistics, all on ``device``."""

    NAMES = ("means", "sh_dc", "sh_rest", "opacity_logits", "log_scales", "quats")

    def __init__(self, g: Gaussians, cfg: TrainConfig, extent: float, device: str | torch.device = "cpu") -> None:
        self.device = torch.device(device)
        g = g.detach().to(device=self.device, dtype=torch.float32).with_sh_degree(cfg.sh_degree)
        params = {"means": g.means, "sh_dc": g.sh[:, :1], "sh_rest": g.sh[:, 1:],
                  "opacity_logits": g.opacity_logits, "log_scales": g.log_scales, "quats": g.quats}
        lrs = {"means": _position_lr(0, cfg, extent), "sh_dc": cfg.feature_lr,
               "sh_rest": cfg.feature_lr * cfg.feature_rest_lr_factor, "opacity_logits": cfg.opacity_lr,
               "log_scales": cfg.scaling_lr, "quats": cfg.rotation_lr}
        self.opt = GaussianAdam({k: v.contiguous() for k, v in params.items()}, lrs)
        self.cfg, self.extent = cfg, extent
        self.reset_stats()

    @property
    def n(self) -> int:
        return int(self.opt.params["means"].shape[0])

    def gaussians(self) -> Gaussians:
        p = self.opt.params
        return Gaussians(p["means"], p["log_scales"], p["quats"], p["opacity_logits"],
                         torch.cat([p["sh_dc"], p["sh_rest"]], dim=1))

    def reset_stats(self) -> None:
        self.grad_accum = torch.zeros(self.n, device=self.device)
        self.denom = torch.zeros(self.n, device=self.device)
        self.max_radii = torch.zeros(self.n, device=self.device)

    @torch.no_grad()
    def accumulate(self, means2d: Tensor, radii: Tensor, width: int, height: int) -> None:
        """Add one view's screen-space statistics (masked arithmetic: no host sync on CUDA)."""
        vis = radii > 0
        torch.maximum(self.max_radii, radii.float(), out=self.max_radii)  # culled radii are 0
        if means2d.grad is None:
            return
        g = means2d.grad * means2d.new_tensor([width / 2.0, height / 2.0])  # pixels -> NDC
        self.grad_accum += torch.where(vis, g.norm(dim=-1), 0.0)
        self.denom += vis

    @torch.no_grad()
    def density_control(self, it: int, means2d: Tensor, radii: Tensor, cam: Camera, gen: torch.Generator,
                        white: bool) -> None:
        """One iteration's density control after the Adam step: accumulate the view's statistics, clear the
        gradients, then densify / prune and reset opacities when the schedule says so.

        Args:
            it: the iteration (1-based).
            means2d: [N, 2] screen-space means of the render (their ``grad`` is the view's statistic).
            radii: [N] screen radii of the render.
            cam: the view.
            gen: CPU generator of the split samples.
            white: white background (INRIA also resets opacities at ``densify_from_iter``).
        """
        cfg = self.cfg
        if it <= cfg.densify_until_iter:
            self.accumulate(means2d, radii, cam.width, cam.height)
        self.opt.zero_grad()
        if it > cfg.densify_until_iter:
            return
        if it > cfg.densify_from_iter and it % cfg.densification_interval == 0:
            self.densify_and_prune(gen, prune_big=it > cfg.opacity_reset_interval > 0)
        if (cfg.opacity_reset_interval > 0 and it % cfg.opacity_reset_interval == 0) or (
                white and it == cfg.densify_from_iter):
            self.reset_opacity()

    @torch.no_grad()
    def densify_and_prune(self, gen: torch.Generator, prune_big: bool) -> dict[str, int]:
        """Clone / split / prune (see the module docstring); ``gen`` is a CPU generator for the split samples."""
        cfg, p = self.cfg, self.opt.params
        grads = self.grad_accum / self.denom
        grads[~torch.isfinite(grads)] = 0.0
        scales = p["log_scales"].detach().exp()
        max_scale = scales.max(dim=1).values
        selected = grads >= cfg.densify_grad_threshold
        if cfg.max_gaussians is not None:
            room = cfg.max_gaussians - self.n
            if room <= 0:
                selected[:] = False
            elif int(selected.sum()) > room:  # keep the largest gradients
                idx = torch.nonzero(selected).flatten()
                keep = idx[grads[idx].topk(room).indices]
                selected[:] = False
                selected[keep] = True
        small = max_scale <= cfg.percent_dense * self.extent
        clone, split = selected & small, selected & ~small
        n0 = self.n
        # clone: exact copies
        extra = {k: v.detach()[clone] for k, v in p.items()}
        # split: 2 children sampled from the parent, scales / (0.8 * 2); samples drawn with the CPU generator
        n_split = int(split.sum())
        if n_split:
            stds = scales[split].repeat(2, 1)
            stds_cpu = stds.cpu()
            samples = torch.normal(torch.zeros_like(stds_cpu), stds_cpu, generator=gen).to(self.device)
            rots = quat_to_rotmat(p["quats"].detach()[split]).repeat(2, 1, 1)
            child_means = (rots @ samples[:, :, None])[:, :, 0] + p["means"].detach()[split].repeat(2, 1)
            child = {k: v.detach()[split].repeat(2, *([1] * (v.dim() - 1))) for k, v in p.items()}
            child["means"] = child_means
            child["log_scales"] = torch.log(stds / (0.8 * 2))
            extra = {k: torch.cat([extra[k], child[k]]) for k in extra}
        self.opt.append(extra)
        n1 = self.n
        prune = torch.zeros(n1, dtype=torch.bool, device=self.device)
        prune[:n0] = split
        opac = torch.sigmoid(self.opt.params["opacity_logits"].detach())
        low_opacity = opac < cfg.min_opacity
        prune |= low_opacity
        if prune_big:
            radii = torch.cat([self.max_radii, torch.zeros(n1 - n0, device=self.device)])
            if cfg.max_screen_size is not None:
                prune |= radii > cfg.max_screen_size
            big = self.opt.params["log_scales"].detach().exp().max(dim=1).values > cfg.max_world_size * self.extent
            prune |= big
        if int(prune.sum()) >= n1:  # never remove everything
            prune[:] = False
        self.opt.prune(~prune)
        self.reset_stats()
        return {"cloned": int(clone.sum()), "split": n_split, "pruned": int(prune.sum()) - n_split}

    @torch.no_grad()
    def reset_opacity(self) -> None:
        o = self.opt.params["opacity_logits"].detach()
        new = torch.minimum(o, torch.logit(torch.tensor(self.cfg.opacity_reset_value)).to(o.device))
        self.opt.replace("opacity_logits", new)

