"""Train 3DGS on NeRF-synthetic lego (../shared/data/lego) on the CPU or a CUDA GPU and score held-out views.

Every 8th view (r_0, r_8, ...) is held out as the test set (the folder has only a train split). Writes
``benchmarks/results/<tag>.{json,md}`` (tag ``train_lego``, or ``train_lego_cuda`` on a GPU) and the INRIA model
folder under ``build/train_lego/`` (git-ignored).

Schedules: ``--preset cpu`` (default: 2500 iterations at 200x200, densify every 20 from 100 to iterations / 2,
opacity reset every 1000, SH +1 every 250, 30k random points, at most 150k Gaussians) or ``--preset inria``
(``TrainConfig``'s defaults, INRIA's recipe: 30k iterations at 800x800, densify every 100 from 500 to 15000,
opacity reset every 3000, SH +1 every 1000, 100k random points, no cap); each schedule flag overrides its preset
value. ``--time-budget-s`` stops the optimisation at a wall-clock budget; the model reached is still evaluated
and saved.

CPU runs: run it alone: two OpenMP programs sharing 2 cores make each other 10x slower (spin-waiting threads); the
recorded run used ``GOMP_SPINCOUNT=10000`` to limit that.

Usage:
    .venv/bin/python benchmarks/train_lego.py [--iterations 3000] [--downscale 4]
    python benchmarks/train_lego.py --device cuda --preset inria --time-budget-s 360
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

from gsw.data.loaders import load_nerf_synthetic
from gsw.train import TrainConfig, resolve_device, train

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "lego"
RESULTS = ROOT / "benchmarks" / "results"
_INRIA = TrainConfig()
# schedule flag -> value, per preset (densify_until None: iterations // 2; max_gaussians 0: no cap)
PRESETS: dict[str, dict[str, float | None]] = {
    "cpu": {"iterations": 2500, "downscale": 4, "init_points": 30_000, "densify_from": 100, "densify_until": None,
            "densify_interval": 20, "opacity_reset": 1000, "sh_interval": 250, "max_gaussians": 150_000},
    "inria": {"iterations": _INRIA.iterations, "downscale": 1, "init_points": _INRIA.init_points,
              "densify_from": _INRIA.densify_from_iter, "densify_until": _INRIA.densify_until_iter,
              "densify_interval": _INRIA.densification_interval, "opacity_reset": _INRIA.opacity_reset_interval,
              "sh_interval": _INRIA.sh_increase_interval, "max_gaussians": 0},
}


def _cpu_name() -> str:
    try:
        for line in open("/proc/cpuinfo", encoding="utf-8"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _load_avg() -> list[float]:
    try:
        return [float(x) for x in open("/proc/loadavg", encoding="utf-8").read().split()[:3]]
    except OSError:
        return []


def write_markdown(summary: dict, path: Path) -> None:
    """Human-readable report next to the JSON."""
    c, m = summary["config"], summary["machine"]
    on_cpu = summary["device"] == "cpu"
    cap = "no cap on the number of Gaussians" if c["max_gaussians"] is None else f"cap {c['max_gaussians']} Gaussians"
    iters = f"{summary['iterations']}"
    if summary["stopped_by_budget"]:
        iters += f" of {summary['iterations_planned']}, stopped by the {summary['time_budget_s']:g} s budget"
    if on_cpu:
        machine = (f"Machine: {m['cpu']}, {m['cores']} cores, torch {summary['torch']} ({m['torch_threads']} "
                   f"threads), {m['platform']}, Python {m['python']}. Load average before/after: "
                   f"{m['loadavg_before']} / {m['loadavg_after']} (other jobs shared the 2 cores; wall times are "
                   "upper bounds).")
    else:
        machine = (f"Machine: {summary['device_name']} (torch {summary['torch']}, CUDA {summary['torch_cuda']}), "
                   f"host {m['cpu']}, {m['cores']} cores, {m['platform']}, Python {m['python']}.")
    lines = [
        f"# 3DGS training on NeRF-synthetic lego ({'CPU' if on_cpu else summary['device_name']})",
        "",
        f"Held-out views (every 8th of the 100 train views: r_0, r_8, ..., {summary['num_test_views']} views), "
        f"{summary['resolution'][0]}x{summary['resolution'][1]}, white background, "
        f"{summary['num_train_views']} training views.",
        "",
        "| metric | value |",
        "|---|---|",
        f"| test PSNR | {summary['test_psnr']:.2f} dB |",
        f"| test SSIM | {summary['test_ssim']:.4f} |",
        f"| Gaussians | {summary['num_gaussians']:,} |",
        f"| iterations | {iters} ({summary['iterations_per_s']:.1f} it/s) |",
        f"| training loop wall time | {summary['train_loop_time_s']:.0f} s |",
        f"| total wall time (load + init + train + eval + save) | {summary['wall_time_s']:.0f} s |",
        f"| process CPU time | {summary['process_cpu_time_s']:.0f} s |",
    ]
    if not on_cpu:
        lines.append(f"| peak GPU memory (allocated) | {summary['gpu_peak_memory_gib']:.2f} GiB |")
    lines += [
        "",
        machine,
        "",
        f"Settings: INRIA recipe (`gsw.train.TrainConfig`), `--preset {summary['preset']}` schedule: "
        f"{c['iterations']} iterations, random init of {c['init_points']:,} points in the box around the cameras' "
        f"look-at point, densify every {c['densification_interval']} from {c['densify_from_iter']} to "
        f"{c['densify_until_iter']} (grad threshold {c['densify_grad_threshold']} in NDC units), opacity reset "
        f"every {c['opacity_reset_interval']} (and at {c['densify_from_iter']} for the white background), SH degree "
        f"+1 every {c['sh_increase_interval']} up to {c['sh_degree']}, position lr {c['position_lr_init']} -> "
        f"{c['position_lr_final']} x extent ({summary['scene_extent']:.3f}), opacity lr {c['opacity_lr']}, "
        f"lambda_dssim {c['lambda_dssim']}, {cap}.",
        "",
    ]
    if on_cpu:
        lines += [f"Environment: {summary.get('env') or {}}. Two OpenMP jobs on the 2 cores slow each other ~10x "
                  "(spin-waiting threads); an earlier attempt run next to the test suite managed 78 iterations in "
                  "4 minutes.", ""]
    lines += [
        f"Reproduce: `{summary['command']}` (see `--help`); the model folder goes to `build/train_lego/`.",
        "",
        "| view | PSNR | SSIM |",
        "|---|---|---|",
    ]
    lines += [f"| {v['name']} | {v['psnr']:.2f} | {v['ssim']:.4f} |" for v in summary["per_view"] or []]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def parse_args() -> argparse.Namespace:
    """Command-line options, with the preset's values filled in for the schedule flags left out."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA, help="the NeRF-synthetic lego folder (default: %(default)s)")
    ap.add_argument("--device", default="auto",
                    help="'auto' (CUDA when gsw was built with it and a GPU is visible, else CPU; default), 'cpu', "
                         "'cuda' or 'cuda:N'")
    ap.add_argument("--preset", choices=tuple(PRESETS), default="cpu",
                    help="schedule the flags below default to (see the module docstring)")
    ap.add_argument("--iterations", type=int)
    ap.add_argument("--downscale", type=float, help="image size divisor: 1 = 800x800, 4 = 200x200")
    ap.add_argument("--init-points", type=int)
    ap.add_argument("--densify-from", type=int)
    ap.add_argument("--densify-until", type=int, help="preset cpu: iterations / 2")
    ap.add_argument("--densify-interval", type=int)
    ap.add_argument("--opacity-reset", type=int)
    ap.add_argument("--sh-interval", type=int)
    ap.add_argument("--max-gaussians", type=int, help="stop densifying above this count (0: no cap)")
    ap.add_argument("--time-budget-s", type=float, default=None,
                    help="stop training after this many seconds of optimisation (then evaluate and save)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tag", default=None, help="result file name (default: train_lego, or train_lego_cuda on a GPU)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args()
    for name, value in PRESETS[args.preset].items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    return args


def main() -> None:
    args = parse_args()
    device = resolve_device(args.device)
    on_cuda = device.type == "cuda"
    tag = args.tag or ("train_lego_cuda" if on_cuda else "train_lego")
    t0 = time.perf_counter()
    load_before = _load_avg()
    train_set = load_nerf_synthetic(args.data, "train", downscale=args.downscale, background=(1, 1, 1))
    test_set = load_nerf_synthetic(args.data, "test", downscale=args.downscale, background=(1, 1, 1))
    load_time = time.perf_counter() - t0
    cfg = TrainConfig(
        iterations=args.iterations,
        densify_from_iter=args.densify_from,
        densify_until_iter=args.densify_until or args.iterations // 2,
        densification_interval=args.densify_interval,
        opacity_reset_interval=args.opacity_reset,
        sh_increase_interval=args.sh_interval,
        init_points=args.init_points,
        max_gaussians=args.max_gaussians or None,
        seed=args.seed,
        log_interval=100,
        max_train_time_s=args.time_budget_s,
        device=str(device),
    )
    if on_cuda:
        torch.cuda.reset_peak_memory_stats(device)
    out_dir = ROOT / "build" / "train_lego" / f"{tag}_model"  # git-ignored
    res = train(train_set, config=cfg, test_set=test_set, output_dir=out_dir, progress=not args.no_progress,
                source=str(args.data))
    wall = time.perf_counter() - t0
    ru = resource.getrusage(resource.RUSAGE_SELF)
    cpu_s = ru.ru_utime + ru.ru_stime
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True).stdout.strip()
    except OSError:
        commit = ""
    tm = res.test_metrics or {}
    device_name = torch.cuda.get_device_name(device) if on_cuda else _cpu_name()
    env_names = ("OMP_NUM_THREADS", "GOMP_SPINCOUNT", "OMP_WAIT_POLICY", "CUDA_VISIBLE_DEVICES")
    summary = {
        "benchmark": f"lego 3DGS training on {'CPU' if not on_cuda else device_name}",
        "data": f"NeRF-synthetic lego, {args.data}, train split only; every 8th view held out as test",
        "device": str(device), "device_name": device_name, "preset": args.preset,
        "command": " ".join([Path(sys.executable).name, "benchmarks/train_lego.py", *sys.argv[1:]]),
        "resolution": [train_set.width, train_set.height],
        "num_train_views": len(train_set), "num_test_views": len(test_set),
        "background": "white",
        "test_psnr": tm.get("psnr"), "test_ssim": tm.get("ssim"),
        "num_gaussians": res.gaussians.num_gaussians,
        "train_loop_time_s": res.train_time_s, "load_time_s": load_time, "wall_time_s": wall,
        "process_cpu_time_s": cpu_s,
        "wall_time_if_uncontended_s": None if on_cuda else cpu_s / max(1, torch.get_num_threads()),
        "gpu_peak_memory_gib": torch.cuda.max_memory_allocated(device) / 2**30 if on_cuda else None,
        "iterations": res.iterations, "iterations_planned": cfg.iterations,
        "iterations_per_s": res.iterations / res.train_time_s,
        "time_budget_s": args.time_budget_s, "stopped_by_budget": res.iterations < cfg.iterations,
        "scene_extent": res.scene_extent,
        "machine": {"cpu": _cpu_name(), "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                    "platform": platform.platform(), "python": platform.python_version(),
                    "loadavg_before": load_before, "loadavg_after": _load_avg()},
        "torch": torch.__version__, "torch_cuda": torch.version.cuda, "git_commit": commit,
        "env": {k: os.environ[k] for k in env_names if k in os.environ},
        "config": cfg.to_dict(),
        "per_view": tm.get("per_view"),
        "history": res.history,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    with open(RESULTS / f"{tag}.json", "w", encoding="utf-8") as f:
        json.dump(summary, f, indent=1)
    write_markdown(summary, RESULTS / f"{tag}.md")
    print(json.dumps({k: summary[k] for k in ("device_name", "test_psnr", "test_ssim", "num_gaussians", "iterations",
                                               "train_loop_time_s", "wall_time_s", "process_cpu_time_s")}, indent=1))


if __name__ == "__main__":
    sys.exit(main())
