"""Training settings (:class:`TrainConfig`, defaults: the INRIA recipe described in :mod:`gsw.train`) and what
:func:`gsw.train.train` returns (:class:`TrainResult`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import torch

from gsw.device import parse_device
from gsw.gaussians import Gaussians, sh_degree_to_num_coeffs

__all__ = ["TrainConfig", "TrainResult"]

_INRIA_ITERATIONS = 30_000
_SCALED_FIELDS = ("densify_from_iter", "densify_until_iter", "densification_interval", "opacity_reset_interval",
                  "sh_increase_interval")


@dataclass
class TrainConfig:
    """Training hyper-parameters; defaults are INRIA's 3DGS recipe (see :mod:`gsw.train`).

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
            :func:`gsw.device.resolve_device`, which :func:`train` applies).
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
            parse_device(self.device)

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

