"""Per-tile walk lengths of the blend backward for bench_cuda.py's cases (BENCHMARKS.md 2s).

For each case: the 16x16 tiles' visited splats (the largest n_contrib of a tile's pixels: the splats the blend
backward walks there), their total and quantiles, the densest tile's walk over the total walk shared by one wave of
`--blocks-per-sm` whole-tile blocks per SM (the quantity `choose_layout_kernel` compares with
LAYOUT_CRITICAL_PATH_FACTOR and LAYOUT_CUT_FACTOR, csrc/core/constants.h), and the chunks beyond each tile's first
at the cut lengths it may choose.

    python benchmarks/tile_counts.py --ply MODEL.ply --cases ply:0:800x800 frustum:100000:800x800

Runs on the CPU too (`--device cpu`; n_contrib is the same on both backends), with `--sms` then naming the GPU.
"""
from __future__ import annotations

import argparse

import torch

from bench_cuda import make_scene, parse_case
from gsw._ext import _C
from gsw.render.rasterize import rasterize

_MIN = int(_C.constants["CUT_LENGTH_MIN"])
CUT_LENGTHS = (_MIN, _MIN * 3 // 2, 2 * _MIN, 3 * _MIN, 4 * _MIN)  # the kernel's cut_length(0 ... 4)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", required=True, help="family:N:WxH, as bench_cuda.py")
    ap.add_argument("--ply", default="../shared/data/ply/sh3_fixture/point_cloud.ply")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sms", type=int, default=0, help="SMs of the GPU (default: the current device's)")
    ap.add_argument("--blocks-per-sm", type=int, default=8, help="resident whole-tile 4-pixel blocks per SM")
    args = ap.parse_args()
    sms = args.sms or torch.cuda.get_device_properties(0).multi_processor_count
    wave = sms * args.blocks_per_sm
    for case in args.cases:
        family, n, w, h = parse_case(case)
        g, cam = make_scene(family, n, w, h, args.ply, args.device)
        with torch.no_grad():
            out = rasterize(g, cam, validate=False)
        v = out.tile_walks()
        most, total = int(v.max()), int(v.sum())
        extra = {L: int(((v - 1).clamp(min=0) // L).sum()) for L in CUT_LENGTHS}
        p90, p99 = torch.quantile(v.double(), torch.tensor([0.9, 0.99], dtype=torch.float64)).tolist()
        print(f"{case}: {v.numel()} tiles, M {int(out.bins.gauss_ids.numel())}, visited {total}, densest {most}, "
              f"p90 / p99 {p90:.0f} / {p99:.0f}, densest / share {most * wave / max(total, 1):.1f} "
              f"(wave {wave}); chunks beyond each tile's first {extra}")


if __name__ == "__main__":
    main()
