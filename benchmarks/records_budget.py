"""The blend backward's records budget: forward+backward time and peak memory per budget, gsplat 1.5.3 beside it.

gsw's deterministic blend backward stores kBlendGrads values per visited tile intersection and reduces them per
Gaussian afterwards (csrc/cuda/rasterize_cuda.cu). Over a budget (`GSW_BLEND_RECORDS_MIB`, read at every call; 0:
no limit) it runs in chunks of whole tiles. For each case and budget this measures, as `bench_cuda.py` does (same
scenes, image kept through the backward, loss = sum(image * fixed weights)): the forward+backward's median time
(CUDA events) and its peak memory over what was allocated before; once per case, gsplat `packed=False` (its faster
mode on these scenes) and the visited records' size (the rows a one-pass backward holds).

    python benchmarks/records_budget.py --ply PLY --budgets 0 64 32 16 8 --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_cuda import cuda_time, env_info, env_setting, fwdbwd_pair, make_scene, parse_case, peak_mb  # noqa: E402

import gsw  # noqa: E402
from gsw._ext import _C  # noqa: E402

BUDGET_ENV = "GSW_BLEND_RECORDS_MIB"


def visited_records_mib(out: gsw.RenderOutput) -> float:
    """Size of a one-pass backward's records: the tiles' walks (`RenderOutput.tile_walks`) x kBlendGrads float32."""
    return float(out.tile_walks().sum()) * _C.constants["BLEND_GRADS"] * 4 / 2**20


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=[
        "frustum:100000:800x800", "heavy:100000:800x800", "frustum:1000000:1920x1080", "frustum:3000000:1920x1080",
        "frustum:1000000:3840x2160", "ply:9080:1920x1080", "ply:9080:3840x2160"])
    ap.add_argument("--budgets", nargs="+", default=["default", "0", "64", "32", "16", "8"],
                    help="MiB values for GSW_BLEND_RECORDS_MIB ('default': unset)")
    ap.add_argument("--ply", default=None)
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--out", required=True)
    ap.add_argument("--commit", default="")
    args = ap.parse_args()
    result = {"env": env_info(args.commit), "reps": args.reps, "warmup": args.warmup,
              "default_budget_mib": _C.constants["RECORDS_BUDGET_MIB"], "cases": []}
    for case in args.cases:
        family, n, w, h = parse_case(case)
        g, cam = make_scene(family, n, w, h, args.ply)
        w_img = torch.rand(3, h, w, device="cuda", generator=torch.Generator("cuda").manual_seed(0))
        (gsw_fwdbwd, reset), (gsplat_fwdbwd, gsplat_reset) = fwdbwd_pair(g, cam, w_img)
        with torch.no_grad():
            rec = visited_records_mib(gsw.rasterize(g, cam, validate=False))
        row: dict = {"case": case, "visited_records_mib": rec,
                     "gsplat_unpacked_fwdbwd_ms": cuda_time(gsplat_fwdbwd, args.reps, args.warmup, gsplat_reset),
                     "gsplat_unpacked_fwdbwd_peak_mb": peak_mb(gsplat_fwdbwd, gsplat_reset), "gsw": {}}
        gsplat_reset()
        for b in args.budgets:
            with env_setting(BUDGET_ENV, None if b == "default" else b):
                row["gsw"][b] = {"fwdbwd_ms": cuda_time(gsw_fwdbwd, args.reps, args.warmup, reset),
                                 "fwdbwd_peak_mb": peak_mb(gsw_fwdbwd, reset)}
            reset()
        gs = row["gsplat_unpacked_fwdbwd_ms"]
        print(f"{case}: records {rec:.1f} MiB; gsplat {gs:.2f} ms {row['gsplat_unpacked_fwdbwd_peak_mb']:.0f} MiB; "
              + "; ".join(f"{b}: {r['fwdbwd_ms']:.2f} ms ({r['fwdbwd_ms'] / gs:.2f}x) {r['fwdbwd_peak_mb']:.0f} MiB"
                          for b, r in row["gsw"].items()), flush=True)
        result["cases"].append(row)
        del g, gsw_fwdbwd, gsplat_fwdbwd, reset, gsplat_reset
        torch.cuda.empty_cache()
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
