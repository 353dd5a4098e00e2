"""`gsw eval` (the report of one watermarked model) and `gsw eval-grid` (methods x bit lengths x seeds)."""

from __future__ import annotations

import argparse
from pathlib import Path

from gsw.cli.common import (AVAILABLE_BITS, add_background_options, add_device_option, add_message_options,
                            background_of, check_output, input_paths, message_from_args, output_file, positive_int,
                            print_json, reading)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Adds ``eval`` and ``eval-grid``."""
    ev = subparsers.add_parser("eval", help="invisibility and robustness report of a watermarked model")
    ev.add_argument("watermarked", help="watermarked INRIA model folder (its cameras are the views; its "
                                        "watermark.json gives the bit length and background)")
    ev.add_argument("--original", required=True, help="the INRIA model folder before embedding")
    add_message_options(ev, claim=True)
    ev.add_argument("--views", type=positive_int, default=None, help="use the first N cameras")
    ev.add_argument("--official", action="store_true", help="also the official code's attack variants")
    ev.add_argument("--lpips", choices=["vgg", "alex", "none"], default="vgg")
    add_background_options(ev, "default: the model's watermark.json, else black")
    add_device_option(ev)
    ev.add_argument("--output", help="also write the markdown report to this new file (never an input)")
    ev.add_argument("--force", action="store_true", help="replace an existing --output file")
    ev.add_argument("--json", action="store_true")
    ev.set_defaults(func=cmd_eval)
    _add_eval_grid_parser(subparsers)


def cmd_eval(args: argparse.Namespace) -> int:
    """Invisibility + robustness report of a watermarked INRIA folder against its original."""
    from gsw._atomic import atomic_write
    from gsw.cli.metadata import at_resolution, read_watermark_json
    from gsw.data import load_inria_model
    from gsw.device import resolve_device
    from gsw.eval.report import evaluate_watermark

    if args.output:  # fail before the long evaluation; written through output_file below
        check_output(Path(args.output), input_paths(args, "watermarked", "original"), args.force)
    info = read_watermark_json(args.watermarked)
    message, num_bits = message_from_args(args, required=True, stored_bits=None if info is None else info.num_bits)
    background = background_of(args, None if info is None else info.background)
    device = resolve_device(args.device)
    with reading(args.watermarked):
        marked = load_inria_model(args.watermarked)
    with reading(args.original):
        original = load_inria_model(args.original)
    cams = marked.cameras if info is None else at_resolution(marked.cameras, info)
    cams = cams if args.views is None else cams[: args.views]
    report = evaluate_watermark(marked.gaussians.to(device), original.gaussians.to(device), cams, message,
                                num_bits=num_bits, official=args.official, background=background,
                                lpips_net=None if args.lpips == "none" else args.lpips)
    text = report.to_markdown()
    if args.output:
        with output_file(Path(args.output), input_paths(args, "watermarked", "original"), args.force) as tmp:
            with atomic_write(tmp, "w") as f:
                f.write(text)
    if args.json:
        print_json(report.to_dict())
    else:
        print(text, end="")
    return 0


def _add_eval_grid_parser(subparsers: argparse._SubParsersAction) -> None:
    from gsw.attacks.presets import IMAGE_ATTACKS, MODEL_ATTACK_NAMES, SWEEPS
    from gsw.eval.grid import METHODS, PAPER_MODEL_ATTACKS, GridSpec

    default = GridSpec()
    grid = subparsers.add_parser(
        "eval-grid", help="methods x bit lengths x seeds: resumable results and paper tables",
        description="Embeds every (method, bits, seed) cell, evaluates it on held-out views and writes one JSON per "
                    "cell, summary.json and summary.md (the paper's tables) into --output; a rerun skips finished "
                    "cells.")
    grid.add_argument("scene", help='INRIA model folder, or "default" for the built-in scene')
    grid.add_argument("--output", required=True, help="grid folder (created; reused to resume)")
    grid.add_argument("--data", help="the model's dataset (NeRF-synthetic / instant-ngp): train split to embed, "
                      "test split to evaluate (default: hold out every 8th of the model's cameras)")
    grid.add_argument("--downscale", type=float, help="image/camera size divisor of an INRIA model (default 1)")
    grid.add_argument("--white", action="store_true", help="white background (INRIA model; the built-in is white)")
    grid.add_argument("--size", type=positive_int, help="render size of the built-in scene (default 64)")
    grid.add_argument("--train-views", type=positive_int,
                      help="embedding views (built-in scene: orbit size, default 24; INRIA: evenly spaced subset)")
    grid.add_argument("--eval-views", type=positive_int, help="use the first N evaluation views")
    grid.add_argument("--methods", nargs="*", default=list(default.methods), metavar="METHOD",
                      help=f"of {', '.join(METHODS)} (default: all)")
    grid.add_argument("--bits", nargs="*", type=positive_int, choices=AVAILABLE_BITS, default=list(default.bits))
    grid.add_argument("--seeds", nargs="*", type=int, default=list(default.seeds))
    grid.add_argument("--epochs", type=positive_int, default=default.epochs)
    grid.add_argument("--image-attacks", nargs="*", default=list(default.image_attacks), metavar="ATTACK",
                      help=f"of {', '.join(IMAGE_ATTACKS)} (default: all)")
    grid.add_argument("--model-attacks", nargs="*", default=list(default.model_attacks), metavar="ATTACK",
                      help=f"of {', '.join(MODEL_ATTACK_NAMES)} (default: the paper's {', '.join(PAPER_MODEL_ATTACKS)})")
    grid.add_argument("--sweeps", nargs="*", default=list(default.sweeps), metavar="ATTACK",
                      help=f"robustness curves, of {', '.join(SWEEPS)} (default: all)")
    grid.add_argument("--lpips", choices=["vgg", "alex", "none"], default="vgg",
                      help="LPIPS term of the embedding loss")
    grid.add_argument("--metric-lpips", choices=["vgg", "alex", "none"], default="vgg",
                      help="LPIPS network of the invisibility metric")
    grid.add_argument("--fpr", type=float, default=default.fpr, help="false-positive rate of a detection")
    add_device_option(grid, default="cpu")
    grid.add_argument("--resume", action=argparse.BooleanOptionalAction, default=True,
                      help="keep finished cells of an earlier run (default); --no-resume recomputes them")
    grid.add_argument("--force", action="store_true", help="replace the settings of a folder holding another grid")
    grid.add_argument("--plots", action="store_true", help="also draw plots/*.png (needs matplotlib)")
    grid.add_argument("--no-progress", action="store_true")
    grid.add_argument("--json", action="store_true", help="print the summary as JSON instead of tables")
    grid.set_defaults(func=cmd_eval_grid)


def _grid_scene(args: argparse.Namespace):
    """The scene of `gsw eval-grid`: the built-in one or an INRIA model folder (+ its dataset)."""
    from gsw.eval.grid import default_grid_scene, load_grid_scene

    if args.scene == "default":
        misplaced = [flag for flag, value in (("--data", args.data), ("--downscale", args.downscale),
                                              ("--white", args.white)) if value]
        if misplaced:
            raise ValueError(f"{', '.join(misplaced)} apply to an INRIA model folder, not the built-in scene")
        return default_grid_scene(size=args.size or 64, views=args.train_views or 24, eval_views=args.eval_views)
    if args.size:
        raise ValueError("--size applies to the built-in scene; an INRIA model's views come from its cameras/data")
    with reading(args.scene):
        return load_grid_scene(args.scene, args.data, downscale=args.downscale or 1.0, white=args.white,
                               train_views=args.train_views, eval_views=args.eval_views)


def cmd_eval_grid(args: argparse.Namespace) -> int:
    """Runs (or resumes) an evaluation grid: methods x bit lengths x seeds on one scene."""
    from gsw.device import resolve_device
    from gsw.eval.grid import GridSpec, lpips_loss_overrides, run_grid

    if args.plots:
        from gsw.eval.plots import require_matplotlib

        require_matplotlib()  # fail before hours of computing, not after
    spec = GridSpec(methods=tuple(args.methods), bits=tuple(args.bits), seeds=tuple(args.seeds),
                    epochs=args.epochs, image_attacks=tuple(args.image_attacks),
                    model_attacks=tuple(args.model_attacks), sweeps=tuple(args.sweeps),
                    embed=lpips_loss_overrides(None if args.lpips == "none" else args.lpips), fpr=args.fpr,
                    lpips_net=None if args.metric_lpips == "none" else args.metric_lpips)
    scene = _grid_scene(args).to(resolve_device(args.device))
    summary = run_grid(spec, scene, args.output, resume=args.resume, force=args.force,
                       progress=not args.no_progress)
    plots = []
    if args.plots:
        from gsw.eval.plots import plot_grid

        plots = plot_grid(args.output)
    if args.json:
        print_json(summary.to_dict())
    else:
        print(summary.to_markdown())
        print(f"{summary.computed} cells computed, {summary.reused} reused; results in {args.output}/ "
              f"(summary.md, summary.json, cells/){''.join(f', {p}' for p in plots)}")
    return 0
