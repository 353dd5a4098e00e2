"""``gsw train``: command-line front end of :func:`gsw.train.train` (``register`` adds it to the `gsw` parser)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from gsw.cli.common import (add_background_options, add_device_option, add_resize_images_option, background_of,
                            check_output, claim_output_folder, input_paths, resized_notice)

__all__ = ["add_train_parser", "register", "run_train", "config_from_args"]


def add_train_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``train`` sub-command.

    Args:
        subparsers: the object returned by ``ArgumentParser.add_subparsers()``.

    Returns:
        The ``train`` parser (``func`` default set to :func:`run_train`).
    """
    p = subparsers.add_parser(
        "train", help="train a 3DGS model from posed images",
        description="Train a 3D Gaussian Splatting model with the INRIA recipe on gsw's rasterizer. DATA is a "
                    "NeRF-synthetic folder (transforms_train.json), an instant-ngp transforms.json (or its folder), "
                    "'default' for the built-in procedural scene, or an INRIA model folder with --images. The "
                    "output folder is an INRIA model folder.")
    p.add_argument("data", help="dataset path, or 'default' for the built-in scene")
    p.add_argument("-o", "--output", required=True,
                   help="new output model folder (created at once; checkpoints are written into it as they come)")
    p.add_argument("--force", action="store_true", help="replace an existing output folder (never an input)")
    p.add_argument("--iterations", type=int, default=30_000,
                   help="iterations (the densification/opacity-reset/SH schedule is compressed proportionally "
                        "unless --no-scale-schedule; default 30000 = INRIA)")
    p.add_argument("--no-scale-schedule", action="store_true",
                   help="keep INRIA's absolute schedule (densify 500..15000) whatever --iterations is")
    p.add_argument("--downscale", type=float, default=1.0, help="image size divisor (e.g. 4: 800 -> 200)")
    p.add_argument("--sh-degree", type=int, default=3, choices=(0, 1, 2, 3))
    add_background_options(p, "default; RGBA images are composited on it", default="white")
    p.add_argument("--init", default="random",
                   help="'random' (INRIA box init), 'points' (dataset point cloud) or a .ply model to start from")
    p.add_argument("--init-points", type=int, default=100_000, help="number of random initial Gaussians")
    p.add_argument("--max-gaussians", type=int, default=None, help="stop densifying above this count")
    p.add_argument("--holdout-every", type=int, default=8,
                   help="hold out every N-th view as test when the dataset has no test split (0: none)")
    p.add_argument("--no-eval", action="store_true", help="skip the test-view evaluation")
    p.add_argument("--images", default=None, help="image folder for an INRIA model folder used as DATA")
    add_resize_images_option(p)
    p.add_argument("--save-iterations", type=int, nargs="*", default=[], help="extra checkpoint iterations")
    p.add_argument("--seed", type=int, default=0)
    add_device_option(p)
    p.add_argument("--time-budget-s", type=float, default=None,
                   help="stop training after this many seconds of optimisation (the model reached is still saved "
                        "and evaluated)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--scene-size", type=int, default=128, help="image size of the built-in scene ('default')")
    p.set_defaults(func=run_train)
    return p


def register(subparsers: argparse._SubParsersAction) -> None:
    """Adds ``train``."""
    add_train_parser(subparsers)


def config_from_args(args: argparse.Namespace):
    """The :class:`~gsw.train.TrainConfig` described by parsed arguments (``--device`` resolved to a concrete
    device).

    Raises:
        ValueError: a bad ``--device`` or ``--time-budget-s``.
        RuntimeError: ``--device`` names a CUDA device that is not usable.
    """
    from gsw.train import TrainConfig, resolve_device  # noqa: PLC0415

    overrides = dict(sh_degree=args.sh_degree, init_points=args.init_points, max_gaussians=args.max_gaussians,
                     seed=args.seed, save_iterations=tuple(args.save_iterations),
                     max_train_time_s=args.time_budget_s, device=str(resolve_device(args.device)))
    if args.no_scale_schedule:
        return TrainConfig(iterations=args.iterations, **overrides)
    return TrainConfig.scaled(args.iterations, **overrides)


def _default_scene_views(size: int, background: tuple[float, float, float]):
    import torch  # noqa: PLC0415

    from gsw.data.loaders import Dataset  # noqa: PLC0415
    from gsw.render.rasterize import rasterize  # noqa: PLC0415
    from gsw.scenes import default_scene  # noqa: PLC0415

    scene = default_scene(width=size, height=size, n_cameras=24, background=background)
    with torch.no_grad():
        imgs = torch.stack([rasterize(scene.gaussians, c, background=scene.background).image.clamp(0, 1)
                            for c in scene.cameras])
    return Dataset(cameras=scene.cameras, images=imgs, alphas=None, names=[c.name for c in scene.cameras],
                   background=scene.background.float(), format="default_scene")


def run_train(args: argparse.Namespace) -> int:
    """Run ``gsw train`` for parsed arguments; returns the exit status (errors propagate to :func:`gsw.cli.main.main`,
    which reports them)."""
    from gsw.data.loaders import detect_format, holdout_indices, load_dataset  # noqa: PLC0415
    from gsw.train import train  # noqa: PLC0415

    background = background_of(args)
    cfg = config_from_args(args)
    inputs = input_paths(args, "images") + [Path(p) for p in (args.data, args.init) if Path(p).exists()]
    check_output(Path(args.output), inputs, args.force)  # fail before loading; claimed below
    if args.data == "default":
        full = _default_scene_views(args.scene_size, background)
        if args.holdout_every >= 2:
            tr_idx, te_idx = holdout_indices(len(full), args.holdout_every)
            train_set, test_set = full.subset(tr_idx), full.subset(te_idx)
        else:
            train_set, test_set = full, None
    else:
        kw = dict(downscale=args.downscale, background=background, holdout_every=args.holdout_every,
                  images_dir=args.images, resize_images=args.resize_images)
        fmt = detect_format(args.data)
        data_path = Path(args.data)
        has_test_file = fmt == "nerf_synthetic" and (
            (data_path.parent if data_path.is_file() else data_path) / "transforms_test.json").is_file()
        split_views = args.holdout_every >= 2 or has_test_file
        train_set = load_dataset(args.data, "train" if split_views or fmt == "nerf_synthetic" else "all", **kw)
        test_set = load_dataset(args.data, "test", **kw) if split_views and not args.no_eval else None
        resized_notice("train", train_set.meta.get("resized", []))
    if args.no_eval:
        test_set = None
    init = args.init
    if init not in ("random", "points"):
        from gsw.io import load_gaussians  # noqa: PLC0415

        init = load_gaussians(init)
    output = claim_output_folder(Path(args.output), inputs, args.force)
    result = train(train_set, config=cfg, init=init, output_dir=output, progress=not args.no_progress,
                   test_set=test_set, source=str(args.data))
    summary = {"output": str(args.output), "device": str(result.device), "iterations": result.iterations,
               "num_gaussians": result.gaussians.num_gaussians, "train_time_s": round(result.train_time_s, 2)}
    if result.test_metrics is not None:
        summary.update(test_psnr=round(result.test_metrics["psnr"], 3), test_ssim=round(result.test_metrics["ssim"], 4))
    print(json.dumps(summary))
    return 0
