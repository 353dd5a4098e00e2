"""Initial Gaussians of a training run: INRIA's random box initialisation or a point cloud."""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.gaussians import rgb_to_sh_dc, Gaussians, sh_degree_to_num_coeffs

__all__ = ["init_box", "points_init", "random_init"]


def _knn_mean_sq_dist(points: Tensor, k: int = 3, chunk: int = 2048) -> Tensor:
    """Mean squared distance to the ``k`` nearest other points (INRIA's ``distCUDA2``), chunked cdist, on the
    points' device."""
    n = points.shape[0]
    kw = {"dtype": points.dtype, "device": points.device}
    if n <= 1:
        return torch.ones(n, **kw)
    k = min(k, n - 1)
    out = torch.empty(n, **kw)
    for s in range(0, n, chunk):
        d = torch.cdist(points[s:s + chunk], points).pow_(2)
        rows = torch.arange(d.shape[0], device=points.device)
        d[rows, rows + s] = float("inf")
        out[s:s + chunk] = d.topk(k, dim=1, largest=False).values.mean(1)
    return out


def init_box(cameras: Sequence[Camera], box_scale: float = 0.33) -> tuple[Tensor, Tensor]:
    """Axis-aligned random-init box from the cameras: centred on the least-squares intersection of the optical
    axes, half size ``box_scale`` x the mean camera distance to it. Returns ``(lo [3], hi [3])`` float64."""
    centers = torch.stack([c.center.detach().double().cpu() for c in cameras])
    dirs = torch.stack([c.c2w.detach().double().cpu()[:3, 2] for c in cameras])
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    eye = torch.eye(3, dtype=torch.float64)
    proj = eye[None] - dirs[:, :, None] * dirs[:, None, :]
    a, b = proj.sum(0), (proj @ centers[:, :, None]).sum(0)[:, 0]
    if len(cameras) >= 2 and float(torch.linalg.matrix_rank(a)) == 3:
        target = torch.linalg.solve(a, b)
    else:  # parallel axes / one camera: a point in front of the cameras
        target = (centers + dirs).mean(0)
    half = box_scale * float((centers - target).norm(dim=1).mean())
    return target - half, target + half


def _make_gaussians(means: Tensor, rgb: Tensor, sh_degree: int, opacity: float,
                    device: str | torch.device) -> Gaussians:
    n = means.shape[0]
    kw = {"dtype": torch.float32, "device": device}
    means = means.to(**kw)
    dist2 = _knn_mean_sq_dist(means).clamp_min(1e-7)
    log_scales = torch.log(dist2.sqrt())[:, None].repeat(1, 3)
    quats = torch.zeros(n, 4, **kw)
    quats[:, 0] = 1.0
    sh = torch.zeros(n, sh_degree_to_num_coeffs(sh_degree), 3, **kw)
    sh[:, 0] = rgb_to_sh_dc(rgb.to(**kw))
    op = torch.full((n,), float(torch.logit(torch.tensor(opacity))), **kw)
    return Gaussians(means, log_scales, quats, op, sh)


def random_init(n: int, lo: Tensor, hi: Tensor, *, sh_degree: int = 3, opacity: float = 0.1,
                seed: int = 0, device: str | torch.device = "cpu") -> Gaussians:
    """INRIA's random initialisation: ``n`` uniform points in the box, near-black colours (``rand / 255``),
    isotropic scales from the 3-nearest-neighbour distance, identity rotations.

    The points are drawn on the CPU (the same for every device) and the Gaussians built on ``device``.
    """
    gen = torch.Generator().manual_seed(seed)
    lo, hi = lo.detach().cpu().double(), hi.detach().cpu().double()
    means = lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=torch.float64)
    rgb = torch.rand(n, 3, generator=gen) / 255.0
    return _make_gaussians(means, rgb, sh_degree, opacity, device)


def points_init(points: Tensor, colors: Tensor | None = None, *, sh_degree: int = 3,
                opacity: float = 0.1, device: str | torch.device = "cpu") -> Gaussians:
    """Initialisation from a point cloud (colours default to grey), built on ``device``."""
    rgb = colors if colors is not None else torch.full_like(points, 0.5)
    return _make_gaussians(points.detach(), rgb.detach(), sh_degree, opacity, device)
