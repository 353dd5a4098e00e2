"""Run the forward blend and the contribution kernel once each on one scene, for a kernel profiler.

Meant to be run under Nsight Compute to compare the two traversals on the same tiles, e.g.

    ncu --clock-control none -k 'regex:^(forward_kernel|contribution_kernel)$' \
        --section SpeedOfLight --section WarpStateStats python benchmarks/profile_kernels.py

Scene: ``gsw.scenes.frustum_scene(N, Camera.from_fov(0.8, W, H), sh_degree=3, seed=0)``, as in bench_cuda.py.
"""

from __future__ import annotations

import argparse

import torch

import gsw
from gsw.camera import Camera
from gsw.scenes import frustum_scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--channels", type=int, default=3, help="contribution weight channels")
    args = ap.parse_args()
    width, height = map(int, args.size.split("x"))
    cam = Camera.from_fov(0.8, width, height)
    g = frustum_scene(args.n, cam, sh_degree=3, seed=0, device="cuda")
    weights = torch.rand(args.channels, height, width, device="cuda")
    with torch.no_grad():
        out = gsw.rasterize(g, cam, validate=False)
        contrib = gsw.contribution(g, cam, weights)
    torch.cuda.synchronize()
    print(f"N={args.n} {width}x{height}: intersections {int(out.bins.num_intersections)}, "
          f"contribution sum {float(contrib.values.sum()):.4g}")


if __name__ == "__main__":
    main()
