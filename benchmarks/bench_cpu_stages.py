"""Per-stage CPU time of one forward+backward render (issue 24's CPU targets), for A/B runs of two builds.

Stages, on the same inputs (100k Gaussians at 800x800, SH 3 by default): projection + SH, tile binning, blend
forward, blend backward, projection/SH backward, and the whole ``rasterize`` + ``image.sum().backward()``.
Each stage is timed with the process CPU time (all threads; on a shared machine it is steadier than the wall
time) and the wall time; the minimum over the repeats is reported, with the 1-minute load average.

``--so PATH`` loads another build of the extension (e.g. the previous commit's, copied aside) instead of
``gsw._C``, so two builds can be compared by alternating processes.

Usage:
    python benchmarks/bench_cpu_stages.py [--family heavy|frustum] [--threads 1] [--repeats 5] [--so PATH]
        [--json OUT]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import time

from bench_cpu import add_scene_args, family_scene, forward_backward_fn


def _load_extension(path: str) -> None:
    """Registers the extension at ``path`` as ``gsw._C`` (before anything imports it)."""
    import gsw
    import torch  # noqa: F401  (the extension links against libtorch: load it first)

    spec = importlib.util.spec_from_file_location("gsw._C", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules["gsw._C"] = module
    gsw._C = module


def _timed(fn, repeats: int) -> dict:
    fn()  # warm-up
    cpus, walls = [], []
    for _ in range(repeats):
        start, cpu = time.perf_counter(), time.process_time()
        fn()
        walls.append(1e3 * (time.perf_counter() - start))
        cpus.append(1e3 * (time.process_time() - cpu))
    return {"cpu_ms": min(cpus), "wall_ms": min(walls), "wall_median_ms": sorted(walls)[len(walls) // 2]}


def run(family: str, n: int, size: int, sh_degree: int, repeats: int) -> dict:
    """Times every stage once per repeat; returns {stage: {cpu_ms, wall_ms, wall_median_ms}}."""
    import torch

    from gsw._ext import _C
    from gsw.render import _ops

    g, cam = family_scene(family, n, size, size, sh_degree)
    cam_args = dict(viewmat=cam.viewmat, fx=float(cam.fx), fy=float(cam.fy), cx=float(cam.cx), cy=float(cam.cy),
                    width=size, height=size)
    inputs = (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)
    a = cam_args

    def project():
        return _ops.project(*inputs, sh_degree, a["viewmat"], a["fx"], a["fy"], a["cx"], a["cy"], size, size,
                            False)

    radii, means2d, conics, depths, colors, opacities, _ = project()
    background = torch.zeros(3)

    def bins():
        return _ops.bins(means2d, conics, opacities, radii, depths, size, size)

    b = bins()

    def blend_forward():
        return _C.rasterize_forward(means2d, conics, colors, opacities, depths, background, bins=b, width=size,
                                    height=size)

    image, alpha, depth, final_T, n_contrib = blend_forward()
    v_image = torch.ones_like(image)

    def blend_backward():
        return _C.rasterize_backward(means2d, conics, colors, opacities, depths, background, bins=b, width=size,
                                     height=size, final_T=final_T, n_contrib=n_contrib, v_image=v_image,
                                     v_alpha=None, v_depth=None)

    v_means2d, v_conics, v_colors, v_opacities, v_depths = blend_backward()

    def project_backward():
        return _ops.project_backward(*inputs, sh_degree, a["viewmat"], a["fx"], a["fy"], a["cx"], a["cy"], size,
                                     size, radii, v_means2d, v_conics, v_depths,
                                     v_colors, v_opacities)

    whole = forward_backward_fn(g, cam)

    out = {"intersections": int(b.num_intersections)}
    for name, fn in (("project", project), ("bin", bins), ("blend_forward", blend_forward),
                     ("blend_backward", blend_backward), ("project_backward", project_backward),
                     ("fwd_bwd", whole)):
        out[name] = _timed(fn, repeats)
    out["load"] = os.getloadavg()[0]
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scene_args(parser, family="heavy", threads=1, repeats=5)
    parser.add_argument("--so", help="path of another build of the extension to load as gsw._C")
    parser.add_argument("--json", help="append the result as one JSON line to this file")
    args = parser.parse_args()
    if args.so:
        _load_extension(args.so)
    import torch

    torch.set_num_threads(args.threads)
    result = dict(family=args.family, n=args.n, size=args.size, sh_degree=args.sh_degree, threads=args.threads,
                  so=args.so or "gsw._C", **run(args.family, args.n, args.size, args.sh_degree, args.repeats))
    stages = [k for k, v in result.items() if isinstance(v, dict)]
    print(f"{args.family} {args.so or 'gsw._C'} threads={args.threads} load={result['load']:.2f} "
          f"M={result['intersections']:,}: " +
          ", ".join(f"{k} {result[k]['cpu_ms']:.1f}/{result[k]['wall_ms']:.1f}" for k in stages) +
          " (cpu/wall ms)", flush=True)
    if args.json:
        with open(args.json, "a") as f:
            f.write(json.dumps(result) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
