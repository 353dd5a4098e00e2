"""Where the serial part of a Ray job goes (#27): imports, `ray.init`, actor start, shutdown, process exit.

Each run is a fresh interpreter (``--child``) that, timing each part from its own start:

1. imports torch and gsw's Ray runner (what ``gsw fingerprint`` imports before any work) and starts CUDA;
2. connects to a new local Ray cluster the way gsw does (:func:`gsw.fingerprint.run.connect_ray`);
3. starts ``--workers`` actors the way gsw does (:class:`gsw.fingerprint.run.RayWorkers`, ``num_gpus`` 1 on CUDA)
   whose warm-up imports torch and gsw and starts CUDA, and waits until every one has answered;
4. ends them and the cluster;

and the parent times the whole process, so that the interpreter's start and exit (the rest) are known too.
Each configuration (``--env NAME=VALUE,...``, e.g. Ray's ``RAY_prestart_worker_first_driver=0``) runs
``--repeats`` times, interleaved with the others. The pair ``num_cpus=N`` in a configuration is not an environment
variable: the local cluster is started with ``ray.init(num_cpus=N)``. Ray prestarts one idle Python worker per CPU
it is given (``--num_prestart_python_workers``), 64 on a 64-core host, while a GPU job needs one per GPU.

    python benchmarks/ray_start.py --workers 4 --device cuda --repeats 3 \
        --env "" --env RAY_prestart_worker_first_driver=0 --env num_cpus=4 --out /tmp/ray_start.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time


def _warm(device: str) -> None:  # pragma: no cover - runs in a Ray worker
    import torch

    import gsw.fingerprint.shared  # noqa: F401 - what a fingerprint worker imports

    if device == "cuda":
        torch.zeros(1, device="cuda")
        torch.cuda.synchronize()


def _child(workers: int, device: str, num_cpus: int | None) -> dict:
    t = {"start": time.time()}
    import torch

    import gsw.fingerprint.run as run

    if device == "cuda":
        torch.zeros(1, device="cuda")
        torch.cuda.synchronize()
    t["imported"] = time.time()
    import ray

    run.connect_ray(None, **({} if num_cpus is None else {"num_cpus": num_cpus}))
    t["ray_init"] = time.time()
    pool = run.RayWorkers(workers, num_gpus=1.0 if device == "cuda" else 0.0, num_cpus=1.0, warm=_warm,
                          warm_args=(device,))
    ready = ray.get([a.run.remote(lambda _s, _p: time.time(), None, None, ()) for a in pool.actors])
    t["actors_ready"] = time.time()
    t["first_ready"] = min(ready)
    pool.shutdown()
    ray.shutdown()
    t["shutdown"] = time.time()
    return t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--env", action="append", default=None,
                    help="a configuration: NAME=VALUE pairs separated by commas ('' : as is); repeatable")
    ap.add_argument("--out", default=None)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--num-cpus", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print("RESULT " + json.dumps(_child(args.workers, args.device, args.num_cpus)), flush=True)
        return 0
    configs = args.env or [""]
    runs: dict[str, list] = {c: [] for c in configs}
    for _ in range(args.repeats):
        for c in configs:
            pairs = dict(kv.split("=", 1) for kv in c.split(",") if kv)
            cpus = ["--num-cpus", pairs.pop("num_cpus")] if "num_cpus" in pairs else []
            env = dict(os.environ, **pairs)
            launched = time.time()
            proc = subprocess.run([sys.executable, __file__, "--child", "--workers", str(args.workers), "--device",
                                   args.device, *cpus], env=env, capture_output=True, text=True)
            ended = time.time()
            line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
            if proc.returncode or not line:
                raise SystemExit(f"child failed ({c!r}): {proc.stderr[-2000:]}")
            t = json.loads(line[0][7:])
            parts = dict(interpreter=t["start"] - launched, imports=t["imported"] - t["start"],
                         ray_init=t["ray_init"] - t["imported"], actors=t["actors_ready"] - t["ray_init"],
                         first_actor=t["first_ready"] - t["ray_init"], shutdown=t["shutdown"] - t["actors_ready"],
                         exit=ended - t["shutdown"], total=ended - launched)
            runs[c].append(parts)
            print(f"{c or 'as is'}: " + ", ".join(f"{k} {v:.2f}" for k, v in parts.items()), flush=True)
    summary = {c: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for c, rs in runs.items()}
    import ray
    import torch

    out = dict(settings=vars(args), runs=runs, median=summary,
               machine=dict(cpus=os.cpu_count(), python=platform.python_version(), torch=torch.__version__,
                            ray=ray.__version__, gpus=[torch.cuda.get_device_name(i)
                                                       for i in range(torch.cuda.device_count())],
                            date=time.strftime("%Y-%m-%d %H:%M:%S %Z")))
    for c, s in summary.items():
        print(f"median {c or 'as is'}: " + ", ".join(f"{k} {v:.2f}" for k, v in s.items()))
    if args.out:
        from gsw._atomic import atomic_write

        with atomic_write(args.out, "w") as f:
            f.write(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
