"""`gsw render` (a model to PNGs) and `gsw info` (build information)."""

from __future__ import annotations

import argparse
from pathlib import Path

from gsw.cli.common import (add_background_options, background_of, input_paths, output_folder, positive_int,
                            print_json, reading)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Adds ``render`` and ``info``."""
    render = subparsers.add_parser("render", help="render a .ply/.splat model to PNGs")
    render.add_argument("model", help="INRIA point_cloud.ply or .splat file")
    render.add_argument("--cameras", help="INRIA cameras.json (default: an orbit)")
    render.add_argument("--orbit", type=positive_int, default=8, help="orbit views")
    render.add_argument("--radius", type=float, default=None, help="orbit radius")
    render.add_argument("--width", type=positive_int, default=512)
    render.add_argument("--height", type=positive_int, default=512)
    add_background_options(render, "default: black")
    render.add_argument("--output", required=True, help="new output folder (never holding the model or cameras)")
    render.add_argument("--force", action="store_true", help="replace an existing output folder")
    render.set_defaults(func=cmd_render)

    info = subparsers.add_parser("info", help="print build information")
    info.set_defaults(func=cmd_info)


def cmd_render(args: argparse.Namespace) -> int:
    """Renders a PLY/.splat model from cameras.json or an orbit."""
    import torch

    from gsw.camera import load_inria_cameras, orbit_cameras
    from gsw.data.images import write_image
    from gsw.io import load_gaussians
    from gsw.render.rasterize import rasterize

    model, out_dir = Path(args.model), Path(args.output)
    g = load_gaussians(model)
    if args.cameras:
        with reading(args.cameras):
            cams = load_inria_cameras(args.cameras)
    else:
        center = g.means.median(dim=0).values
        radius = args.radius or float(3.0 * (g.means - center).norm(dim=1).median())
        cams = orbit_cameras(center.tolist(), radius, args.orbit, width=args.width, height=args.height)
    bg = background_of(args)
    with output_folder(out_dir, input_paths(args, "model", "cameras"), args.force) as tmp, torch.no_grad():
        for i, cam in enumerate(cams):
            out = rasterize(g, cam, background=bg)
            name = cam.name or f"view_{i:03d}"
            write_image(tmp / f"{Path(name).stem}.png", out.image)
    print(f"rendered {len(cams)} views of {len(g):,} Gaussians to {out_dir}/")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    """Prints the build information as JSON."""
    import gsw

    print_json(gsw.build_info())
    return 0
