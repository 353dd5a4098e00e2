"""How a render's blending work is spread over its 16x16 tiles (issue 24: the dense-tile tail).

For each case (family:N:WxH, the scenes of bench_cuda.py; `ply:0:WxH` with `--ply` for a trained model) it
renders once and reports, per tile: its intersections (the tile's list length) and its visited splats (the
largest n_contrib of its pixels, `RenderOutput.tile_walks`: what the blend backward and the contribution walk).
Over the tiles with a visited splat ("busy"): mean, median, 90th / 99th percentile and maximum, and the tail ratio
max / mean. A tile is one thread block of every blending kernel, so a kernel whose busy tiles fit in one wave of
blocks lasts at least as long as its densest tile. Also what the CUDA blend backward chooses its layout by
(BENCHMARKS.md 2s): the densest tile's walk over the total walk shared by one wave of `--blocks-per-sm` whole-tile
blocks per SM (compared there with LAYOUT_CRITICAL_PATH_FACTOR and LAYOUT_CUT_FACTOR, csrc/core/constants.h), and
the chunks beyond each tile's first at the cut lengths it may choose.

    python benchmarks/tile_load.py --device cpu --sms 132 --cases frustum:100000:800x800 --json out.json

On the CPU (n_contrib is the same on both backends) `--sms` names the GPU.
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


def tile_load(case: str, ply: str | None, device: str, wave: int) -> dict:
    """Per-tile intersection and visited-splat statistics of one case, and the layout quantities for a wave of
    `wave` whole-tile blocks (see the module docstring)."""
    import gsw
    from gsw._ext import _C

    family, n, w, h = parse_case(case)
    g, cam = make_scene(family, n, w, h, ply, device=device)
    with torch.no_grad():
        out = gsw.rasterize(g, cam, validate=False)
    visited = out.tile_walks()
    lengths = out.bins.tile_offsets.diff().cpu()
    busy = visited > 0
    most, total = int(visited.max()), int(visited.sum())
    return dict(case=case, gaussians=int(g.means.shape[0]), tiles=visited.numel(), busy_tiles=int(busy.sum()),
                intersections=int(lengths.sum()), visited_total=total,
                intersections_per_busy_tile=_stats(lengths[busy]), visited_per_busy_tile=_stats(visited[busy]),
                wave=wave, densest_over_share=round(most * wave / max(total, 1), 2),
                extra_chunks={L: int(((visited - 1).clamp(min=0) // L).sum()) for L in _C.constants["CUT_LENGTHS"]},
                device=str(device), gsw=gsw.__version__)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["frustum:100000:800x800"])
    ap.add_argument("--ply", default="../shared/data/ply/sh3_fixture/point_cloud.ply")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sms", type=int, default=0, help="SMs of the GPU (default: the current device's)")
    ap.add_argument("--blocks-per-sm", type=int, default=8, help="resident whole-tile 4-pixel blocks per SM")
    ap.add_argument("--json")
    args = ap.parse_args()
    wave = (args.sms or torch.cuda.get_device_properties(0).multi_processor_count) * args.blocks_per_sm
    rows = []
    for case in args.cases:
        r = tile_load(case, args.ply, args.device, wave)
        v, m = r["visited_per_busy_tile"], r["intersections_per_busy_tile"]
        print(f"{case}: {r['busy_tiles']:,} of {r['tiles']:,} tiles busy; visited per busy tile mean {v['mean']} "
              f"p50 {v['p50']:.0f} p90 {v['p90']:.0f} p99 {v['p99']:.0f} max {v['max']} (max/mean {v['tail']}); "
              f"intersections mean {m['mean']} max {m['max']}; visited total {r['visited_total']:,}, densest / share "
              f"{r['densest_over_share']} (wave {wave}); chunks beyond each tile's first {r['extra_chunks']}",
              flush=True)
        rows.append(r)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
