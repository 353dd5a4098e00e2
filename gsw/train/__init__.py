"""3D Gaussian Splatting training (the INRIA recipe) on gsw's rasterizer.

Training runs on the CPU by default; ``TrainConfig(device="cuda")`` trains on a GPU (``"auto"``: on one when usable).

Example:
    >>> from gsw.train import TrainConfig, train  # doctest: +SKIP
    >>> from gsw.data.loaders import load_nerf_synthetic  # doctest: +SKIP
    >>> res = train(load_nerf_synthetic("lego", "train", downscale=4), config=TrainConfig.scaled(3000),
    ...             test_set=load_nerf_synthetic("lego", "test", downscale=4), output_dir="out")  # doctest: +SKIP
"""

from __future__ import annotations

from gsw.train.trainer import (
    TrainConfig,
    TrainResult,
    evaluate,
    init_box,
    points_init,
    random_init,
    resolve_device,
    train,
)

__all__ = ["TrainConfig", "TrainResult", "evaluate", "init_box", "points_init", "random_init", "resolve_device",
           "train"]
