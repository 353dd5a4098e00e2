"""How a render's blending work is spread over its 16x16 tiles (issue 24: the dense-tile tail).

For each case (family:N:WxH, the scenes of bench_cuda.py; `ply:0:WxH` with `--ply` for a trained model) it
projects, bins and blends once and reports, per tile: its intersections (the tile's list length) and its visited
splats (the largest n_contrib of its pixels: what the blend backward and the contribution walk). Over the tiles
with a visited splat ("busy"): mean, median, 90th / 99th percentile and maximum, and the tail ratio max / mean. A
tile is one thread block of every blending kernel, so a kernel whose busy tiles fit in one wave of blocks lasts at
least as long as its densest tile.

    python benchmarks/tile_load.py --device cpu --cases frustum:100000:800x800 --json out.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_cuda import make_scene, parse_case  # noqa: E402


def _stats(x: torch.Tensor) -> dict:
    """Mean, quantiles and maximum of a 1-D tensor of counts (empty: zeros)."""
    if x.numel() == 0:
        return dict(mean=0.0, p50=0.0, p90=0.0, p99=0.0, max=0, tail=0.0)
    xf = x.double()
    q = torch.quantile(xf, torch.tensor([0.5, 0.9, 0.99], dtype=torch.float64))
    mean = float(xf.mean())
    return dict(mean=round(mean, 1), p50=float(q[0]), p90=float(q[1]), p99=float(q[2]), max=int(x.max()),
                tail=round(float(x.max()) / mean, 2))


def tile_load(case: str, ply: str | None, device: str) -> dict:
    """Per-tile intersection and visited-splat statistics of one case (see the module docstring)."""
    import gsw
    from gsw.constants import TILE_SIZE
    from gsw.render.rasterize import bin_gaussians, blend, project

    family, n, w, h = parse_case(case)
    g, cam = make_scene(family, n, w, h, ply, device=device)
    with torch.no_grad():
        proj = project(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, cam, g.sh_degree)
        bins = bin_gaussians(proj, w, h)
        *_, n_contrib = blend(proj, w, h, torch.zeros(3, device=device))
    tx, ty = -(-w // TILE_SIZE), -(-h // TILE_SIZE)
    pad = torch.zeros(ty * TILE_SIZE, tx * TILE_SIZE, dtype=torch.int32, device=device)
    pad[:h, :w] = n_contrib
    visited = pad.reshape(ty, TILE_SIZE, tx, TILE_SIZE).amax(dim=(1, 3)).flatten().cpu()
    lengths = bins.tile_offsets.diff().cpu()
    busy = visited > 0
    return dict(case=case, gaussians=int(g.means.shape[0]), tiles=tx * ty, busy_tiles=int(busy.sum()),
                intersections=int(lengths.sum()), visited_total=int(visited.sum()),
                intersections_per_busy_tile=_stats(lengths[busy]), visited_per_busy_tile=_stats(visited[busy]),
                device=str(device), gsw=gsw.__version__)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["frustum:100000:800x800"])
    ap.add_argument("--ply", default="../shared/data/ply/sh3_fixture/point_cloud.ply")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--json")
    args = ap.parse_args()
    rows = []
    for case in args.cases:
        r = tile_load(case, args.ply, args.device)
        v, m = r["visited_per_busy_tile"], r["intersections_per_busy_tile"]
        print(f"{case}: {r['busy_tiles']:,} of {r['tiles']:,} tiles busy; visited per busy tile mean {v['mean']} "
              f"p50 {v['p50']:.0f} p90 {v['p90']:.0f} p99 {v['p99']:.0f} max {v['max']} (max/mean {v['tail']}); "
              f"intersections mean {m['mean']} max {m['max']}", flush=True)
        rows.append(r)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
