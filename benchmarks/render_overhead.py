"""Host overhead of one render (#24, #26): ``gsw.rasterize`` forward and forward + backward on a tiny scene (50
Gaussians, 16x16, so the kernels cost next to nothing), through the eager path (:func:`gsw.render._ops.call`: the
ops' implementations in a plain autograd function) and through the custom-op dispatch, in one process.

Median of ``--repeats`` timed calls after ``--warmup`` (synchronising the device after each call), in microseconds;
the two paths alternate for ``--rounds`` rounds (a shared machine's speed drifts) and each reports the median of its
rounds' medians.

    python benchmarks/render_overhead.py [--device cuda] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--warmup", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()

    from gsw.camera import Camera
    from gsw.render import _ops
    from gsw.render.rasterize import rasterize
    from gsw.scenes import random_gaussians

    torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    g = random_gaussians(50, seed=0).to(dev)
    leaves = [t.requires_grad_() for t in (g.means, g.sh, g.opacity_logits, g.log_scales, g.quats)]
    cam = Camera.look_at((0.0, -4.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.8, 16, 16)

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    def forward():
        rasterize(g, cam, validate=False)

    def forward_backward():
        rasterize(g, cam, validate=False).image.sum().backward()

    def timed(fn) -> float:
        for _ in range(args.warmup):
            fn()
        sync()
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            fn()
            sync()
            times.append(1e6 * (time.perf_counter() - t0))
        return statistics.median(times)

    samples: dict[str, dict[str, list[float]]] = {p: {"forward_us": [], "forward_backward_us": []}
                                                   for p in ("eager", "dispatched")}
    traced = _ops._traced
    for _ in range(args.rounds):
        for path, timings in samples.items():
            _ops._traced = traced if path == "eager" else (lambda a: True)
            try:
                timings["forward_us"].append(timed(forward))
                timings["forward_backward_us"].append(timed(forward_backward))
            finally:
                _ops._traced = traced
            for t in leaves:
                t.grad = None
    rows = {path: {k: statistics.median(v) for k, v in timings.items()} | {"rounds": timings}
            for path, timings in samples.items()}
    for path, row in rows.items():
        print(path, json.dumps({k: round(v, 1) for k, v in row.items() if k != "rounds"}), flush=True)
    out = dict(device=str(dev), gpu=torch.cuda.get_device_name(dev) if dev.type == "cuda" else None,
               cpu=platform.processor() or platform.machine(), threads=args.threads, torch=torch.__version__,
               python=platform.python_version(), date=time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
               warmup=args.warmup, repeats=args.repeats, rounds=args.rounds, rows=rows)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
