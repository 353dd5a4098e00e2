"""The INRIA 3D Gaussian Splatting training recipe on :func:`gsw.render.rasterize.rasterize`.

Recipe (Kerbl et al. 2023, ``graphdeco-inria/gaussian-splatting``), every number a :class:`TrainConfig` field:

- one random training view per iteration (shuffled passes), loss ``(1 - 0.2) L1 + 0.2 (1 - SSIM)``;
- Adam (eps 1e-15) with per-tensor learning rates: positions ``1.6e-4 * extent`` decaying log-linearly to
  ``1.6e-6 * extent`` over the run, ``f_dc`` 2.5e-3, ``f_rest`` 2.5e-3 / 20, opacity 0.05 (the value of the
  original release and of the 3D-GSW code base; later INRIA versions use 0.025), scaling 5e-3, rotation 1e-3.
  ``extent`` is INRIA's ``getNerfppNorm`` radius (1.1 x the largest camera distance from their centroid);
- SH degree raised by one every 1000 iterations up to the model degree;
- densification from iteration 500 to 15000 every 100: the screen-space positional gradient is accumulated
  over the views where a Gaussian is visible; Gaussians whose mean gradient reaches 2e-4 are cloned when small
  (largest scale <= 1% of the extent) and split into two (samples from the parent, scales / 1.6) when large;
  Gaussians with opacity < 0.005 are pruned, and after the first opacity reset also those larger than 20 px on
  screen or 10% of the extent in world space; opacities are reset to <= 0.01 every 3000 iterations (and at
  iteration 500 on a white background, as INRIA does).

**Screen-space gradient units.** INRIA's 2e-4 threshold applies to the gradient w.r.t. NDC coordinates
(``x_ndc = 2 u / W - 1``). Our ``means2d`` are pixels, so the NDC gradient is the pixel gradient times
``(W / 2, H / 2)``; we accumulate ``|(g_u W / 2, g_v H / 2)|`` and keep INRIA's threshold unchanged.

**Screen-size pruning.** INRIA's code zeroes ``max_radii2D`` just before it tests it, so its 20 px criterion never
fires; here the criterion uses the radii accumulated since the last densification (``max_screen_size=None``
restores INRIA's effective behaviour).

**Shorter schedules.** :meth:`TrainConfig.scaled` compresses every iteration-based field proportionally, for
CPU runs of a few thousand iterations; ``max_train_time_s`` stops the loop at a wall-clock budget instead.

**Devices.** ``TrainConfig.device`` (``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"``, see :func:`resolve_device`)
is where the Gaussians, images, densification statistics, Adam state and background live and where the loss, SSIM
and the test evaluation run. Random initial points, the view order and the split samples come from seeded CPU
generators (and are moved to the device), so a seed gives the same random choices on every device. Outside the rasterizer, the loop
waits for the device only at log iterations, progress-bar redraws, densification steps and checkpoints; on CUDA the
parameters are checked for NaN/Inf at log iterations only (on the CPU at every iteration). Checkpoints are written
from CPU float32 copies.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor

import gsw
from gsw.camera import Camera
from gsw.constants import SH_C0, SH_COLOR_OFFSET
from gsw.data.loaders import Dataset, save_inria_model, scene_extent
from gsw.gaussians import Gaussians, quat_to_rotmat, sh_degree_to_num_coeffs
from gsw.metrics.image import psnr, ssim
from gsw.render.rasterize import rasterize
from gsw.train.optim import GaussianAdam
from gsw.progress import Progress

__all__ = ["TrainConfig", "TrainResult", "train", "evaluate", "random_init", "points_init", "init_box",
           "resolve_device"]

_INRIA_ITERATIONS = 30_000
_SCALED_FIELDS = ("densify_from_iter", "densify_until_iter", "densification_interval", "opacity_reset_interval",
                  "sh_increase_interval")


@dataclass
class TrainConfig:
    """Training hyper-parameters; defaults are INRIA's 3DGS recipe (see the module docstring).

    Attributes:
        iterations: number of optimisation steps (one view each).
        sh_degree: SH degree of the model (the active degree ramps up to it).
        position_lr_init: position lr at iteration 0, times the scene extent.
        position_lr_final: position lr at ``position_lr_max_steps``, times the scene extent.
        position_lr_delay_mult: INRIA's warm-up multiplier (only with ``position_lr_delay_steps > 0``).
        position_lr_delay_steps: warm-up length (INRIA: 0).
        position_lr_max_steps: decay horizon (``None``: ``iterations``).
        feature_lr: ``f_dc`` learning rate.
        feature_rest_lr_factor: ``f_rest`` lr is ``feature_lr`` times this (1/20).
        opacity_lr: opacity-logit learning rate.
        scaling_lr: log-scale learning rate.
        rotation_lr: quaternion learning rate.
        lambda_dssim: weight of ``1 - SSIM`` in the loss.
        densify_from_iter: first iteration of densification.
        densify_until_iter: last iteration of densification (and of gradient statistics).
        densification_interval: iterations between densification steps.
        densify_grad_threshold: mean NDC-gradient norm that triggers clone/split.
        percent_dense: clone/split boundary, fraction of the scene extent.
        opacity_reset_interval: iterations between opacity resets (0 disables).
        opacity_reset_value: opacities are clamped to at most this at a reset.
        min_opacity: prune below this opacity.
        max_screen_size: prune Gaussians whose radius exceeded this many pixels (after the first reset;
            ``None`` disables).
        max_world_size: prune Gaussians larger than this fraction of the extent (after the first reset).
        sh_increase_interval: iterations between SH degree increments.
        init_points: number of random initial points (``init="random"``).
        init_opacity: initial opacity.
        init_box_scale: half size of the random-init box, as a fraction of the mean camera distance to the
            point the cameras look at (0.33 reproduces INRIA's +-1.3 cube on NeRF-synthetic).
        max_gaussians: stop densifying above this count (``None``: unlimited).
        ssim_window: SSIM window size.
        seed: RNG seed (view order, initialisation, split samples).
        log_interval: iterations between history records.
        save_iterations: iterations at which checkpoints are written (the last one always is).
        scene_extent: override the camera-derived extent.
        max_train_time_s: stop the optimisation loop once it has run this many seconds (``None``: no limit);
            the last iteration reached is logged, checkpointed and evaluated like the final one. The stopping
            iteration depends on the machine, so a budget makes runs irreproducible.
        device: where training runs: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"`` (see
            :func:`resolve_device`, which :func:`train` applies).
    """

    iterations: int = 30_000
    sh_degree: int = 3
    position_lr_init: float = 1.6e-4
    position_lr_final: float = 1.6e-6
    position_lr_delay_mult: float = 0.01
    position_lr_delay_steps: int = 0
    position_lr_max_steps: int | None = None
    feature_lr: float = 2.5e-3
    feature_rest_lr_factor: float = 1.0 / 20.0
    opacity_lr: float = 0.05
    scaling_lr: float = 5e-3
    rotation_lr: float = 1e-3
    lambda_dssim: float = 0.2
    densify_from_iter: int = 500
    densify_until_iter: int = 15_000
    densification_interval: int = 100
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    opacity_reset_interval: int = 3000
    opacity_reset_value: float = 0.01
    min_opacity: float = 0.005
    max_screen_size: float | None = 20.0
    max_world_size: float = 0.1
    sh_increase_interval: int = 1000
    init_points: int = 100_000
    init_opacity: float = 0.1
    init_box_scale: float = 0.33
    max_gaussians: int | None = None
    ssim_window: int = 11
    seed: int = 0
    log_interval: int = 50
    save_iterations: tuple[int, ...] = ()
    scene_extent: float | None = None
    max_train_time_s: float | None = None
    device: str = "cpu"

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        sh_degree_to_num_coeffs(self.sh_degree)
        if self.densification_interval < 1 or self.sh_increase_interval < 1:
            raise ValueError("densification_interval and sh_increase_interval must be >= 1")
        if not 0 <= self.lambda_dssim <= 1:
            raise ValueError(f"lambda_dssim must be in [0, 1], got {self.lambda_dssim}")
        if self.max_train_time_s is not None and self.max_train_time_s <= 0:
            raise ValueError(f"max_train_time_s must be > 0, got {self.max_train_time_s}")
        self.device = str(self.device)
        if self.device != "auto":
            _parse_device(self.device)

    @classmethod
    def scaled(cls, iterations: int, **overrides: Any) -> "TrainConfig":
        """INRIA's recipe compressed to ``iterations``: densification window, densification interval, opacity
        reset interval and SH ramp are multiplied by ``iterations / 30000``, with floors for short runs
        (densify at most every 20 iterations, opacity resets at most every 1000, SH steps at most every 100).

        Args:
            iterations: the run length.
            **overrides: any other field (applied after scaling; an explicit value wins).
        """
        base = cls()
        s = iterations / _INRIA_ITERATIONS
        scaled = {name: max(1, int(round(getattr(base, name) * s))) for name in _SCALED_FIELDS}
        # Floors for short runs: gradient statistics over at least 20 views between densifications, at least
        # 1000 iterations (or the whole run) to recover from an opacity reset, SH steps >= 100 iterations.
        scaled["densification_interval"] = max(scaled["densification_interval"], min(20, iterations))
        scaled["opacity_reset_interval"] = max(scaled["opacity_reset_interval"], min(1000, iterations))
        scaled["sh_increase_interval"] = max(scaled["sh_increase_interval"], min(100, iterations))
        scaled.update(overrides)
        return replace(base, iterations=iterations, **scaled)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dict."""
        d = asdict(self)
        d["save_iterations"] = list(self.save_iterations)
        return d


@dataclass
class TrainResult:
    """What :func:`train` returns.

    Attributes:
        gaussians: the trained model (detached, float32, on ``device``).
        history: one record per ``log_interval``: iteration, loss, psnr (of that view), num_gaussians, time_s.
        test_metrics: ``{"psnr", "ssim", "per_view": [...]}`` on the test set, or ``None``.
        train_time_s: wall time of the optimisation loop (excludes the final evaluation).
        total_time_s: wall time including initialisation, checkpoints and evaluation.
        config: the configuration used.
        output_dir: where checkpoints were written, or ``None``.
        scene_extent: extent used for learning rates and densification.
        iterations: optimisation steps run (below ``config.iterations`` when ``max_train_time_s`` stopped the
            loop).
        device: the device training ran on.
    """

    gaussians: Gaussians
    history: list[dict[str, float]]
    test_metrics: dict[str, Any] | None
    train_time_s: float
    total_time_s: float
    config: TrainConfig
    output_dir: Path | None
    scene_extent: float
    iterations: int
    device: torch.device


# ------------------------------------------------------------------------------------------- device


_DEVICE_HELP = "device must be 'auto', 'cpu', 'cuda' or 'cuda:N'"


def _parse_device(device: str | torch.device) -> torch.device:
    """``device`` as a CPU or CUDA :class:`torch.device`, without checking that it is usable.

    Raises:
        ValueError: not a CPU or CUDA device.
    """
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"{_DEVICE_HELP}, got {device!r}") from exc
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"{_DEVICE_HELP} (gsw's rasterizer has CPU and CUDA backends), got {device!r}")
    return dev


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """The device to train on, checked to be usable.

    Args:
        device: ``"auto"`` (the current CUDA device when gsw was built with CUDA and torch sees a GPU, else the
            CPU), ``"cpu"``, ``"cuda"`` (the current CUDA device), ``"cuda:N"`` or a :class:`torch.device`.

    Returns:
        ``cpu`` or ``cuda:N`` (always with an index).

    Raises:
        ValueError: ``device`` is not a CPU or CUDA device.
        RuntimeError: a CUDA device was requested but gsw was built without CUDA (``gsw.build_info()["cuda"]``
            is false), torch sees no usable GPU, or the index is out of range.

    Example:
        >>> from gsw.train import resolve_device
        >>> resolve_device("cpu")
        device(type='cpu')
    """
    if str(device) == "auto":
        return resolve_device("cuda" if gsw.build_info()["cuda_available"] else "cpu")
    dev = _parse_device(device)
    if dev.type == "cpu":
        return dev
    if not gsw.build_info()["cuda"]:
        raise RuntimeError(f"device {str(device)!r} requested but gsw was built without CUDA "
                           "(gsw.build_info()['cuda'] is False); rebuild gsw with CUDA or use device='cpu'")
    if not torch.cuda.is_available():
        raise RuntimeError(f"device {str(device)!r} requested but torch.cuda.is_available() is False (torch "
                           f"{torch.__version__}, CUDA runtime {torch.version.cuda}); use device='cpu'")
    index = torch.cuda.current_device() if dev.index is None else dev.index
    if index >= torch.cuda.device_count():
        raise RuntimeError(f"device {str(device)!r} requested but torch sees {torch.cuda.device_count()} "
                           "CUDA device(s)")
    return torch.device("cuda", index)


# ------------------------------------------------------------------------------------------- init


def _rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    return (rgb - SH_COLOR_OFFSET) / SH_C0


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
    sh[:, 0] = _rgb_to_sh_dc(rgb.to(**kw))
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


# ------------------------------------------------------------------------------------------- helpers


def _as_views(data: Any, what: str) -> tuple[list[Camera], Tensor, Tensor | None, Dataset | None]:
    if isinstance(data, Dataset):
        return list(data.cameras), data.images, data.background, data
    if isinstance(data, (tuple, list)) and len(data) == 2:
        cams, images = data
        cams = list(cams)
        images = torch.stack(list(images)) if not isinstance(images, Tensor) else images
        if images.dim() != 4 or images.shape[1] != 3 or images.shape[0] != len(cams):
            raise ValueError(f"{what}: images must be [V={len(cams)}, 3, H, W], got {list(images.shape)}")
        for c in cams:
            if (c.height, c.width) != tuple(images.shape[-2:]):
                raise ValueError(f"{what}: camera {c.name!r} is {c.width}x{c.height} but images are "
                                 f"{images.shape[-1]}x{images.shape[-2]}")
        return cams, images.float(), None, None
    raise TypeError(f"{what} must be a gsw.data.Dataset or a (cameras, images) pair, got {type(data).__name__}")


@torch.no_grad()
def evaluate(gaussians: Gaussians, cameras: Sequence[Camera], images: Tensor, *,
             background: Tensor | Sequence[float] = (1.0, 1.0, 1.0), sh_degree: int | None = None,
             names: Sequence[str] | None = None) -> dict[str, Any]:
    """PSNR / SSIM of renders against images (mean over views, plus ``per_view``).

    Renders are clamped to ``[0, 1]`` before scoring. Rendering and scoring run on the Gaussians' device (the
    images are moved there one view at a time).
    """
    per_view = []
    bg = torch.as_tensor(background, dtype=gaussians.dtype, device=gaussians.device)
    for i, cam in enumerate(cameras):
        img = rasterize(gaussians, cam, sh_degree=sh_degree, background=bg).image.clamp(0, 1)
        ref = images[i].to(img)
        per_view.append({"name": names[i] if names else cam.name, "psnr": float(psnr(img, ref)),
                         "ssim": float(ssim(img, ref))})
    n = max(1, len(per_view))
    return {"psnr": sum(v["psnr"] for v in per_view) / n, "ssim": sum(v["ssim"] for v in per_view) / n,
            "num_views": len(per_view), "per_view": per_view}


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


def _write_cfg_args(folder: Path, cfg: TrainConfig, white: bool, device: torch.device, source: str) -> None:
    """INRIA's ``cfg_args`` (a ``Namespace`` repr read by SIBR and the INRIA render script)."""
    from gsw._atomic import atomic_write  # noqa: PLC0415

    text = (f"Namespace(data_device={device.type!r}, eval=True, images='images', model_path={str(folder)!r}, "
            f"resolution=-1, sh_degree={cfg.sh_degree}, source_path={source!r}, white_background={white})")
    with atomic_write(folder / "cfg_args", "w") as f:
        f.write(text)


# ------------------------------------------------------------------------------------------- trainer


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


def train(data: Dataset | tuple[Sequence[Camera], Tensor], *, config: TrainConfig | None = None,
          init: str | Gaussians = "random", output_dir: str | os.PathLike | None = None,
          progress: bool = True, test_set: Dataset | tuple[Sequence[Camera], Tensor] | None = None,
          background: Sequence[float] | Tensor | None = None, source: str = "") -> TrainResult:
    """Train a 3DGS model with the INRIA recipe (see the module docstring).

    Args:
        data: training views: a :class:`~gsw.data.Dataset` or ``(cameras, images [V, 3, H, W])``.
        config: hyper-parameters (default: INRIA's 30k recipe; see :meth:`TrainConfig.scaled` for short runs).
        init: ``"random"`` (uniform in :func:`init_box`), ``"points"`` (the dataset's point cloud) or a
            :class:`~gsw.gaussians.Gaussians` to start from.
        output_dir: write checkpoints there as an INRIA model folder
            (``point_cloud/iteration_N/point_cloud.ply`` + ``cameras.json`` + ``cfg_args``) plus
            ``train_result.json``. Files are replaced atomically.
        progress: show a progress bar on stderr.
        test_set: held-out views scored (PSNR/SSIM) at the end.
        background: RGB background (default: the dataset's, else white).
        source: dataset path recorded in ``cfg_args``.

    Returns:
        A :class:`TrainResult`.

    Raises:
        RuntimeError: ``config.device`` names a CUDA device that is not usable (see :func:`resolve_device`).

    Example:
        >>> from gsw.scenes import default_scene
        >>> from gsw.train import TrainConfig, train
        >>> import gsw
        >>> scene = default_scene(width=32, height=32, n_cameras=4)
        >>> imgs = torch.stack([gsw.rasterize(scene.gaussians, c, background=scene.background).image
        ...                     for c in scene.cameras])
        >>> res = train((scene.cameras, imgs), config=TrainConfig.scaled(20, init_points=500), progress=False)
        >>> res.gaussians.num_gaussians > 0
        True
    """
    t_start = time.perf_counter()
    cfg = config or TrainConfig()
    device = resolve_device(cfg.device)
    cams, images, ds_bg, ds = _as_views(data, "data")
    if background is not None:
        bg = torch.as_tensor(background, dtype=torch.float32).flatten()
    elif ds_bg is not None:
        bg = ds_bg.float()
    else:
        bg = torch.ones(3)
    if bg.shape != (3,):
        raise ValueError(f"background must be 3 numbers, got {background!r}")
    white = bool(torch.allclose(bg.cpu(), torch.ones(3)))
    bg, images = bg.to(device), images.to(device)
    test = _as_views(test_set, "test_set") if test_set is not None else None
    extent = cfg.scene_extent if cfg.scene_extent is not None else scene_extent(cams)[1]
    gen = torch.Generator().manual_seed(cfg.seed)  # CPU: view order and split samples, the same on every device

    if isinstance(init, Gaussians):
        g0 = init
    elif init == "random":
        lo, hi = init_box(cams, cfg.init_box_scale)
        g0 = random_init(cfg.init_points, lo, hi, sh_degree=cfg.sh_degree, opacity=cfg.init_opacity, seed=cfg.seed,
                         device=device)
    elif init == "points":
        if ds is None or ds.points is None:
            raise ValueError("init='points' needs a Dataset with a point cloud (points)")
        g0 = points_init(ds.points, ds.point_colors, sh_degree=cfg.sh_degree, opacity=cfg.init_opacity,
                         device=device)
    else:
        raise ValueError(f"init must be 'random', 'points' or a Gaussians, got {init!r}")
    state = _State(g0, cfg, extent, device)

    out_dir = Path(output_dir) if output_dir is not None else None
    all_cams = cams + (list(test[0]) if test is not None else [])
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        _write_cfg_args(out_dir, cfg, white, device, source)
    saves = set(int(i) for i in cfg.save_iterations)

    history: list[dict[str, float]] = []
    active_sh = 0 if not isinstance(init, Gaussians) else min(cfg.sh_degree, init.sh_degree)
    order: list[int] = []
    # running means as float64 device tensors: read back only when logged or drawn (no per-step sync on CUDA)
    ema_loss: Tensor | None = None
    ema_psnr: Tensor | None = None
    bar = Progress(cfg.iterations, "train", enabled=progress)
    t_loop = time.perf_counter()
    for it in range(1, cfg.iterations + 1):
        state.opt.set_lr("means", _position_lr(it, cfg, extent))
        if it % cfg.sh_increase_interval == 0 and active_sh < cfg.sh_degree:
            active_sh += 1
        if not order:
            order = torch.randperm(len(cams), generator=gen).tolist()
        vi = order.pop()
        cam, gt = cams[vi], images[vi]
        g = state.gaussians()
        out = rasterize(g, cam, sh_degree=active_sh, background=bg,
                        validate=device.type == "cpu" or it % cfg.log_interval == 0)
        out.means2d.retain_grad()
        img = out.image
        l1 = (img - gt).abs().mean()
        loss = (1.0 - cfg.lambda_dssim) * l1
        if cfg.lambda_dssim > 0:
            loss = loss + cfg.lambda_dssim * (1.0 - ssim(img, gt, window_size=cfg.ssim_window))
        loss.backward()
        with torch.no_grad():
            state.opt.step()
            if it <= cfg.densify_until_iter:
                state.accumulate(out.means2d, out.radii, cam.width, cam.height)
            state.opt.zero_grad()
            if it <= cfg.densify_until_iter:
                if it > cfg.densify_from_iter and it % cfg.densification_interval == 0:
                    state.densify_and_prune(gen, prune_big=it > cfg.opacity_reset_interval > 0)
                if (cfg.opacity_reset_interval > 0 and it % cfg.opacity_reset_interval == 0) or (
                        white and it == cfg.densify_from_iter):
                    state.reset_opacity()
            lv = loss.detach().double()
            pv = psnr(img.detach().clamp(0, 1), gt).double()
            ema_loss = lv if ema_loss is None else 0.6 * ema_loss + 0.4 * lv
            ema_psnr = pv if ema_psnr is None else 0.6 * ema_psnr + 0.4 * pv
            last = it == cfg.iterations or (
                cfg.max_train_time_s is not None and time.perf_counter() - t_loop >= cfg.max_train_time_s)
            if it % cfg.log_interval == 0 or it == 1 or last:
                history.append({"iteration": it, "loss": float(lv), "loss_ema": float(ema_loss), "psnr": float(pv),
                                "psnr_ema": float(ema_psnr), "num_gaussians": state.n, "sh_degree": active_sh,
                                "time_s": time.perf_counter() - t_loop})
            if bar.due:
                bar.update(1, loss=round(float(ema_loss), 4), psnr=round(float(ema_psnr), 2), n=state.n)
            else:
                bar.update(1)
            if out_dir is not None and (it in saves or last):
                save_inria_model(out_dir, state.gaussians().detach(), all_cams, it)
            if last:
                break
    bar.close()
    train_time = time.perf_counter() - t_loop  # the last step's history record synchronised the device
    final = state.gaussians().detach().clone()
    test_metrics = None
    if test is not None:
        test_metrics = evaluate(final, test[0], test[1], background=bg,
                                names=test[3].names if test[3] is not None else None)
        if progress:
            print(f"test: PSNR {test_metrics['psnr']:.2f} dB  SSIM {test_metrics['ssim']:.4f}  "
                  f"({test_metrics['num_views']} views, {final.num_gaussians} Gaussians, {train_time:.0f} s)",
                  file=__import__("sys").stderr)
    result = TrainResult(final, history, test_metrics, train_time, time.perf_counter() - t_start, cfg, out_dir,
                         extent, iterations=it, device=device)
    if out_dir is not None:
        from gsw._atomic import atomic_write  # noqa: PLC0415

        summary = {"iterations": it, "device": str(device), "num_gaussians": final.num_gaussians,
                   "train_time_s": train_time, "total_time_s": result.total_time_s, "scene_extent": extent,
                   "test": test_metrics, "config": cfg.to_dict(), "history": history}
        with atomic_write(out_dir / "train_result.json", "w") as f:
            json.dump(summary, f, indent=1)
    return result
