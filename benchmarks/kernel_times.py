"""Per-kernel GPU time of gsw's forward and forward+backward (torch.profiler), to see where a render's time goes.

For each case (family:N:WxH, the scenes of bench_cuda.py) it runs `--reps` forwards (`validate=False`, no grad) and
`--reps` forward+backwards (loss = sum(image * fixed weights); gradients reset before each, so none is accumulated)
and `--reps` contributions (`gsw.contribution` with 3 weight channels) under the profiler after `--warmup` untimed
runs and prints every CUDA kernel's (and memcpy/memset's) mean time per iteration, largest first, with its share.

    python benchmarks/kernel_times.py --cases heavy:1000000:1920x1080 frustum:3000000:1920x1080 --json out.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_cuda import make_scene, parse_case, trainable  # noqa: E402


def profile(fn, reps: int, warmup: int) -> list[tuple[str, float]]:
    """(kernel name, mean device ms per call) of fn's CUDA kernels, largest first."""
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=acts) as prof:
        for _ in range(reps):
            fn()
        torch.cuda.synchronize()
    times: dict[str, float] = {}
    for e in prof.key_averages():
        t = getattr(e, "self_device_time_total", None)
        if t is None:
            t = e.self_cuda_time_total
        if t > 0 and e.device_type == torch.autograd.DeviceType.CUDA:
            times[e.key] = times.get(e.key, 0.0) + t / 1e3 / reps
    return sorted(times.items(), key=lambda kv: -kv[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=["heavy:1000000:1920x1080", "frustum:3000000:1920x1080"])
    ap.add_argument("--ply", default="../shared/data/ply/sh3_fixture/point_cloud.ply")
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--json")
    args = ap.parse_args()
    import gsw

    out = []
    for case in args.cases:
        family, n, w, h = parse_case(case)
        g, cam = make_scene(family, n, w, h, args.ply)
        weights = torch.rand(3, h, w, device="cuda", generator=torch.Generator("cuda").manual_seed(0))

        def fwd():
            with torch.no_grad():
                gsw.rasterize(g, cam, validate=False)

        params, g_train = trainable(g)

        def fwdbwd():
            for p in params:
                p.grad = None
            (gsw.rasterize(g_train, cam, validate=False).image * weights).sum().backward()

        def contrib():
            gsw.contribution(g, cam, weights)

        row = dict(case=case, forward=profile(fwd, args.reps, args.warmup), fwdbwd=profile(fwdbwd, args.reps, args.warmup),
                   contribution=profile(contrib, args.reps, args.warmup))
        out.append(row)
        for phase in ("forward", "fwdbwd", "contribution"):
            total = sum(t for _, t in row[phase])
            print(f"{case} {phase}: {total:.3f} ms of kernels")
            for name, t in row[phase][:14]:
                print(f"  {t:8.3f} ms {100 * t / total:5.1f} %  {name[:110]}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
