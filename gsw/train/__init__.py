"""3D Gaussian Splatting training: the INRIA recipe on :func:`gsw.render.rasterize.rasterize`.

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

**Devices.** ``TrainConfig.device`` (``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"``, see
:func:`gsw.device.resolve_device`) is where the Gaussians, images, densification statistics, Adam state and
background live and where the loss, SSIM and the test evaluation run. Random initial points, the view order and the
split samples come from seeded CPU generators (and are moved to the device), so a seed gives the same random
choices on every device. Outside the rasterizer, the loop waits for the device only at log iterations,
progress-bar redraws, densification steps and checkpoints; on CUDA the parameters are checked for NaN/Inf at log
iterations only (on the CPU at every iteration). Checkpoints are written from CPU float32 copies.

Modules: :mod:`~gsw.train.config` (:class:`TrainConfig`, :class:`TrainResult`), :mod:`~gsw.train.init` (initial
Gaussians), :mod:`~gsw.train.densify` (parameters, Adam and density control), :mod:`~gsw.train.optim` (Adam with
row surgery) and :mod:`~gsw.train.loop` (:func:`train`, :func:`evaluate`).

Example:
    >>> from gsw.train import TrainConfig, train  # doctest: +SKIP
    >>> from gsw.data.loaders import load_nerf_synthetic  # doctest: +SKIP
    >>> res = train(load_nerf_synthetic("lego", "train", downscale=4), config=TrainConfig.scaled(3000),
    ...             test_set=load_nerf_synthetic("lego", "test", downscale=4), output_dir="out")  # doctest: +SKIP
"""

from __future__ import annotations

from gsw.device import resolve_device
from gsw.train.config import TrainConfig, TrainResult
from gsw.train.init import init_box, points_init, random_init
from gsw.train.loop import evaluate, train

__all__ = ["TrainConfig", "TrainResult", "evaluate", "init_box", "points_init", "random_init", "resolve_device",
           "train"]
