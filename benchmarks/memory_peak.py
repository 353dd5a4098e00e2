"""What is allocated at the peak of one forward+backward: gsw against gsplat 1.5.3 (`packed=False`), per tensor.

For each case, one forward+backward of each renderer (the `fwdbwd` of `bench_cuda.py`: loss = sum(image * fixed
weights), gradients reset before) runs under `torch.cuda.memory._record_memory_history`. The allocation events of
that run are replayed (allocated at `alloc`, released at `free_requested`: the caching allocator's logical size,
what `torch.cuda.max_memory_allocated` counts); at the largest total, the live allocations made during the run are
listed with the Python line that made them (innermost frame in gsw, gsplat or this script; C++ allocations carry
the line of the op call that made them) and their sizes. Memory allocated before the run (inputs, parameters,
weights) is not counted, as in `bench_cuda.py`'s peak. `--keep-image` keeps each renderer's image alive through its
backward, as `bench_cuda.py` (and a training loop) does; without it nothing is kept but the parameters.

    python benchmarks/memory_peak.py --cases frustum:1000000:1920x1080 ply:9080:3840x2160 --ply PLY --out OUT.json
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_cuda import env_info, fwdbwd_pair, make_scene, parse_case  # noqa: E402

_OURS = ("/gsw/", "/gsplat/", "memory_peak.py")


def _site(frames: list[dict]) -> str:
    """The innermost frame in gsw, gsplat or this script, as 'file:line function'."""
    for f in frames:
        name = f.get("filename", "")
        if any(k in name for k in _OURS) and "/torch/" not in name:
            short = name.split("/gsw/")[-1] if "/gsw/" in name else name.split("/")[-1]
            return f"{short}:{f.get('line')} {f.get('name')}"
    return "(no gsw/gsplat frame)"


def peak_breakdown(fn) -> dict:
    """Runs fn once under the allocator's history; returns the peak (MiB, over what was live before) and the live
    allocations at it, grouped by allocation site."""
    torch.cuda.synchronize()
    torch.cuda.memory._record_memory_history(max_entries=1_000_000, stacks="python")
    try:
        fn()
        torch.cuda.synchronize()
        snap = torch.cuda.memory._snapshot()
    finally:
        torch.cuda.memory._record_memory_history(enabled=None)
    trace = snap["device_traces"][torch.cuda.current_device()]
    live: dict[int, tuple[int, str]] = {}
    total = best = 0
    best_live: dict[int, tuple[int, str]] = {}
    for ev in trace:
        if ev["action"] == "alloc":
            live[ev["addr"]] = (ev["size"], _site(ev.get("frames", [])))
            total += ev["size"]
            if total > best:
                best, best_live = total, dict(live)
        elif ev["action"] == "free_requested" and ev["addr"] in live:
            total -= live.pop(ev["addr"])[0]
    groups: dict[str, list[int]] = collections.defaultdict(list)
    for size, site in best_live.values():
        groups[site].append(size)
    rows = sorted(({"site": s, "mib": sum(v) / 2**20, "tensors": len(v),
                    "sizes_mib": sorted((round(x / 2**20, 2) for x in v), reverse=True)[:8]}
                   for s, v in groups.items()), key=lambda r: -r["mib"])
    return {"peak_mib": best / 2**20, "live_at_peak": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=["frustum:1000000:1920x1080"])
    ap.add_argument("--ply", default=None)
    ap.add_argument("--out", required=True)
    ap.add_argument("--commit", default="", help="the gsw commit measured, for the record")
    ap.add_argument("--keep-image", action="store_true",
                    help="keep the rendered image alive through the backward (as a training loop and bench_cuda.py do)")
    args = ap.parse_args()
    result = {"env": env_info(args.commit), "budget_mib_setting": os.environ.get("GSW_BLEND_RECORDS_MIB", ""),
              "keep_image": args.keep_image, "cases": []}
    for case in args.cases:
        family, n, w, h = parse_case(case)
        g, cam = make_scene(family, n, w, h, args.ply)
        w_img = torch.rand(3, h, w, device="cuda", generator=torch.Generator("cuda").manual_seed(0))
        (gsw_fwdbwd, gsw_reset), (gsplat_fwdbwd, gsplat_reset) = fwdbwd_pair(g, cam, w_img, keep_image=args.keep_image)
        row: dict = {"case": case}
        for name, fn, reset in (("gsw", gsw_fwdbwd, gsw_reset), ("gsplat_unpacked", gsplat_fwdbwd, gsplat_reset)):
            for _ in range(2):  # warm-up (gsplat's JIT, the caching allocator)
                fn()
                reset()
            row[name] = peak_breakdown(fn)
            reset()
            print(f"{case} {name}: peak {row[name]['peak_mib']:.1f} MiB", flush=True)
            for r in row[name]["live_at_peak"][:10]:
                print(f"    {r['mib']:8.1f} MiB  {r['tensors']:3d} x  {r['site']}  {r['sizes_mib'][:4]}", flush=True)
        result["cases"].append(row)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
