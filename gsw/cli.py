"""The `gsw` command line: `gsw demo`, `gsw render`, `gsw info`.

Run `gsw <command> --help` for the options of each command.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Sequence

import torch


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _timed(fn, repeats: int) -> tuple[float, object]:
    """Median wall time (s) of `repeats` calls and the last result."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return sorted(times)[len(times) // 2], result


def cmd_demo(args: argparse.Namespace) -> int:
    """Renders the built-in scene (no downloads), times forward/backward, writes PNGs."""
    import gsw
    from gsw.imageio import write_image
    from gsw.scenes import default_scene

    out_dir = Path(args.output)
    out_dir.mkdir(parents=True, exist_ok=True)
    scene = default_scene(width=args.width, height=args.height, n_cameras=args.views)
    g, bg = scene.gaussians, scene.background
    print(f"gsw {gsw.__version__} demo: built-in scene, {len(g):,} Gaussians (SH degree "
          f"{g.sh_degree}), {len(scene.cameras)} views at {args.width}x{args.height}, "
          f"{torch.get_num_threads()} threads")
    params = [t.requires_grad_() for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]
    rows = []
    for i, cam in enumerate(scene.cameras):
        fwd, out = _timed(lambda: gsw.rasterize(g, cam, background=bg), args.repeats)

        def fwd_bwd():
            for p in params:
                p.grad = None
            gsw.rasterize(g, cam, background=bg).image.sum().backward()

        both, _ = _timed(fwd_bwd, args.repeats)
        path = write_image(out_dir / f"view_{i:03d}.png", out.image)
        rows.append(dict(view=i, forward_ms=1e3 * fwd, forward_backward_ms=1e3 * both,
                         visible=int(out.visible.sum()), file=str(path)))
    print(f"{'view':>4} {'forward ms':>11} {'fwd+bwd ms':>11} {'visible':>8}  file")
    for r in rows:
        print(f"{r['view']:>4} {r['forward_ms']:>11.1f} {r['forward_backward_ms']:>11.1f} "
              f"{r['visible']:>8,}  {r['file']}")
    med = lambda k: sorted(r[k] for r in rows)[len(rows) // 2]  # noqa: E731
    print(f"median: forward {med('forward_ms'):.1f} ms, forward+backward "
          f"{med('forward_backward_ms'):.1f} ms; images in {out_dir}/")
    if args.json:
        json.dump(dict(build=gsw.build_info(), views=rows), sys.stdout, indent=2)
        print()
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    """Renders a PLY/.splat model from cameras.json or an orbit."""
    import gsw
    from gsw.camera import load_inria_cameras
    from gsw.imageio import write_image

    model = Path(args.model)
    g = gsw.load_gaussians(model)
    if args.cameras:
        cams = load_inria_cameras(args.cameras)
    else:
        center = g.means.median(dim=0).values
        radius = args.radius or float(3.0 * (g.means - center).norm(dim=1).median())
        cams = gsw.orbit_cameras(center.tolist(), radius, args.orbit, width=args.width,
                                 height=args.height)
    out_dir = Path(args.output)
    if out_dir.resolve() == model.resolve().parent and not args.force:
        raise SystemExit("refusing to write renders into the model's own folder; pass --force")
    out_dir.mkdir(parents=True, exist_ok=True)
    bg = (1.0, 1.0, 1.0) if args.white else (0.0, 0.0, 0.0)
    with torch.no_grad():
        for i, cam in enumerate(cams):
            out = gsw.rasterize(g, cam, background=bg)
            name = cam.name or f"view_{i:03d}"
            write_image(out_dir / f"{Path(name).stem}.png", out.image)
    print(f"rendered {len(cams)} views of {len(g):,} Gaussians to {out_dir}/")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    """Prints the build information as JSON."""
    import gsw

    json.dump(gsw.build_info(), sys.stdout, indent=2)
    print()
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the `gsw` command."""
    parser = argparse.ArgumentParser(prog="gsw", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="render the built-in scene and time the rasterizer")
    demo.add_argument("--output", default="gsw-demo", help="output folder (default: gsw-demo)")
    demo.add_argument("--width", type=_positive_int, default=256)
    demo.add_argument("--height", type=_positive_int, default=256)
    demo.add_argument("--views", type=_positive_int, default=4)
    demo.add_argument("--repeats", type=_positive_int, default=3, help="timing repeats per view")
    demo.add_argument("--json", action="store_true", help="also print the results as JSON")
    demo.set_defaults(func=cmd_demo)

    render = sub.add_parser("render", help="render a .ply/.splat model to PNGs")
    render.add_argument("model", help="INRIA point_cloud.ply or .splat file")
    render.add_argument("--cameras", help="INRIA cameras.json (default: an orbit)")
    render.add_argument("--orbit", type=_positive_int, default=8, help="orbit views")
    render.add_argument("--radius", type=float, default=None, help="orbit radius")
    render.add_argument("--width", type=_positive_int, default=512)
    render.add_argument("--height", type=_positive_int, default=512)
    render.add_argument("--white", action="store_true", help="white background")
    render.add_argument("--output", required=True, help="output folder")
    render.add_argument("--force", action="store_true", help="allow writing next to the model")
    render.set_defaults(func=cmd_render)

    info = sub.add_parser("info", help="print build information")
    info.set_defaults(func=cmd_info)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `gsw` command."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as err:
        print(f"gsw {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
