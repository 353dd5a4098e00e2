"""The training loop of :func:`train` (the INRIA recipe, see :mod:`gsw.train`) and :func:`evaluate`."""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.data.loaders import Dataset, save_inria_model, scene_extent
from gsw.device import resolve_device
from gsw.gaussians import Gaussians
from gsw.metrics.image import psnr, ssim
from gsw.progress import Progress
from gsw.render.rasterize import rasterize
from gsw.train.config import TrainConfig, TrainResult
from gsw.train.densify import _position_lr, _State
from gsw.train.init import init_box, points_init, random_init

__all__ = ["train", "evaluate"]


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


def _write_cfg_args(folder: Path, cfg: TrainConfig, white: bool, device: torch.device, source: str) -> None:
    """INRIA's ``cfg_args`` (a ``Namespace`` repr read by SIBR and the INRIA render script)."""
    from gsw._atomic import atomic_write  # noqa: PLC0415

    text = (f"Namespace(data_device={device.type!r}, eval=True, images='images', model_path={str(folder)!r}, "
            f"resolution=-1, sh_degree={cfg.sh_degree}, source_path={source!r}, white_background={white})")
    with atomic_write(folder / "cfg_args", "w") as f:
        f.write(text)


def train(data: Dataset | tuple[Sequence[Camera], Tensor], *, config: TrainConfig | None = None,
          init: str | Gaussians = "random", output_dir: str | os.PathLike | None = None,
          progress: bool = True, test_set: Dataset | tuple[Sequence[Camera], Tensor] | None = None,
          background: Sequence[float] | Tensor | None = None, source: str = "") -> TrainResult:
    """Train a 3DGS model with the INRIA recipe (see the module docstring).

    Args:
        data: training views: a :class:`~gsw.data.Dataset` or ``(cameras, images [V, 3, H, W])``.
        config: hyper-parameters (default: INRIA's 30k recipe; see :meth:`TrainConfig.scaled` for short runs).
        init: ``"random"`` (uniform in :func:`init_box`), ``"points"`` (the dataset's point cloud) or a
            :class:`~gsw.gaussians.Gaussians` to start from. Training renders SH degree 0 first and adds a
            degree every ``config.sh_increase_interval`` iterations, except from a ``Gaussians`` init, which
            starts at ``min(config.sh_degree, init.sh_degree)`` (resuming a trained model keeps its degree;
            pass ``init.with_sh_degree(0)`` to ramp from degree 0).
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
        RuntimeError: ``config.device`` names a CUDA device that is not usable (see :func:`gsw.device.resolve_device`).

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
    bg = _background(background, ds_bg)
    white = bool(torch.allclose(bg, torch.ones(3)))
    test = _as_views(test_set, "test_set") if test_set is not None else None
    extent = cfg.scene_extent if cfg.scene_extent is not None else scene_extent(cams)[1]
    state = _State(_initial_gaussians(init, cams, ds, cfg, device), cfg, extent, device)
    out_dir = Path(output_dir) if output_dir is not None else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        _write_cfg_args(out_dir, cfg, white, device, source)
    run = _Run(cfg, state, cams, images.to(device), bg.to(device), white, extent, out_dir,
               cams + (list(test[0]) if test is not None else []))
    active_sh = 0 if not isinstance(init, Gaussians) else min(cfg.sh_degree, init.sh_degree)
    it, history, train_time = _optimise(run, active_sh, progress)
    final = state.gaussians().detach().clone()
    test_metrics = None
    if test is not None:
        test_metrics = evaluate(final, test[0], test[1], background=run.bg,
                                names=test[3].names if test[3] is not None else None)
        if progress:
            print(f"test: PSNR {test_metrics['psnr']:.2f} dB  SSIM {test_metrics['ssim']:.4f}  "
                  f"({test_metrics['num_views']} views, {final.num_gaussians} Gaussians, {train_time:.0f} s)",
                  file=sys.stderr)
    result = TrainResult(final, history, test_metrics, train_time, time.perf_counter() - t_start, cfg, out_dir,
                         extent, iterations=it, device=device)
    if out_dir is not None:
        _write_result(out_dir, result)
    return result


@dataclass
class _Run:
    """What the optimisation loop works on (images and background on the training device)."""

    cfg: TrainConfig
    state: _State
    cams: list[Camera]
    images: Tensor
    bg: Tensor
    white: bool
    extent: float
    out_dir: Path | None
    all_cams: list[Camera]


def _background(background: Sequence[float] | Tensor | None, dataset_bg: Tensor | None) -> Tensor:
    """[3] CPU float background: the argument, else the dataset's, else white."""
    if background is not None:
        bg = torch.as_tensor(background, dtype=torch.float32).flatten()
    elif dataset_bg is not None:
        bg = dataset_bg.float()
    else:
        bg = torch.ones(3)
    if bg.shape != (3,):
        raise ValueError(f"background must be 3 numbers, got {background!r}")
    return bg.cpu()


def _initial_gaussians(init: str | Gaussians, cams: Sequence[Camera], ds: Dataset | None, cfg: TrainConfig,
                       device: torch.device) -> Gaussians:
    """The starting model of ``init`` (see :func:`train`)."""
    if isinstance(init, Gaussians):
        return init
    if init == "random":
        lo, hi = init_box(cams, cfg.init_box_scale)
        return random_init(cfg.init_points, lo, hi, sh_degree=cfg.sh_degree, opacity=cfg.init_opacity,
                           seed=cfg.seed, device=device)
    if init == "points":
        if ds is None or ds.points is None:
            raise ValueError("init='points' needs a Dataset with a point cloud (points)")
        return points_init(ds.points, ds.point_colors, sh_degree=cfg.sh_degree, opacity=cfg.init_opacity,
                           device=device)
    raise ValueError(f"init must be 'random', 'points' or a Gaussians, got {init!r}")


def _optimise(run: _Run, active_sh: int, progress: bool) -> tuple[int, list[dict[str, float]], float]:
    """The optimisation loop: returns the last iteration, the history records and the loop's wall time (s)."""
    cfg, state = run.cfg, run.state
    device = state.device
    gen = torch.Generator().manual_seed(cfg.seed)  # CPU: view order and split samples, the same on every device
    saves = set(int(i) for i in cfg.save_iterations)
    history: list[dict[str, float]] = []
    order: list[int] = []
    # running means as float64 device tensors: read back only when logged or drawn (no per-step sync on CUDA)
    ema_loss: Tensor | None = None
    ema_psnr: Tensor | None = None
    bar = Progress(cfg.iterations, "train", enabled=progress)
    background = run.bg.to(device)  # once: a host-to-device copy per render would synchronise every iteration
    t_loop = time.perf_counter()
    for it in range(1, cfg.iterations + 1):
        state.opt.set_lr("means", _position_lr(it, cfg, run.extent))
        if it % cfg.sh_increase_interval == 0 and active_sh < cfg.sh_degree:
            active_sh += 1
        if not order:
            order = torch.randperm(len(run.cams), generator=gen).tolist()
        vi = order.pop()
        cam, gt = run.cams[vi], run.images[vi]
        out = rasterize(state.gaussians(), cam, sh_degree=active_sh, background=background,
                        validate=device.type == "cpu" or it % cfg.log_interval == 0)
        out.means2d.retain_grad()
        img = out.image
        loss = (1.0 - cfg.lambda_dssim) * (img - gt).abs().mean()
        if cfg.lambda_dssim > 0:
            loss = loss + cfg.lambda_dssim * (1.0 - ssim(img, gt, window_size=cfg.ssim_window))
        loss.backward()
        with torch.no_grad():
            state.opt.step()
            state.density_control(it, out.means2d, out.radii, cam, gen, run.white)
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
            if run.out_dir is not None and (it in saves or last):
                save_inria_model(run.out_dir, state.gaussians().detach(), run.all_cams, it)
            if last:
                break
    bar.close()
    return it, history, time.perf_counter() - t_loop  # the last history record synchronised the device


def _write_result(out_dir: Path, result: TrainResult) -> None:
    """``train_result.json``: iterations, device, size, times, extent, test metrics, config and history."""
    from gsw._atomic import atomic_write  # noqa: PLC0415

    summary = {"iterations": result.iterations, "device": str(result.device),
               "num_gaussians": result.gaussians.num_gaussians, "train_time_s": result.train_time_s,
               "total_time_s": result.total_time_s, "scene_extent": result.scene_extent,
               "test": result.test_metrics, "config": result.config.to_dict(), "history": result.history}
    with atomic_write(out_dir / "train_result.json", "w") as f:
        json.dump(summary, f, indent=1)
