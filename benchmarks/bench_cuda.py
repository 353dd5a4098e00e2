"""gsw CUDA rasterizer vs gsplat 1.5.3, side by side on identical scenes (one GPU, one run).

Scenes: `gsw.scenes.frustum_scene(N, Camera.from_fov(0.8, W, H), sh_degree=3, seed=0)` for
N in {100k, 1M, 3M} at 800x800 and 1920x1080, float32 on the GPU. Timed (CUDA events, median of
`--reps` after `--warmup` untimed runs), whole pipeline from the raw Gaussian tensors to the
image:

* forward: `gsw.rasterize` / `gsplat.rasterization` under `torch.no_grad()`;
* forward+backward: the same with gradients, loss = sum(image * fixed random weights),
  `loss.backward()` (gradients reset before each run, outside the timed region);
* contribution (gsw only): `gsw.contribution(g, cam, weights[3, H, W])`, reported against
  gsw's forward.

gsplat gets pre-activated scales/opacities (its API takes them; the activation is not timed) and
default settings otherwise (packed, 16x16 tiles, eps2d 0.3 as ours). Peak memory is
`torch.cuda.max_memory_allocated()` during one run minus what was allocated before it (the
scene and, for gsplat, its activated inputs).

    python benchmarks/bench_cuda.py --out benchmarks/results/cuda.json --md benchmarks/results/cuda.md
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import time
from typing import Callable

import torch

import gsw
from gsw.camera import Camera
from gsw.gaussians import Gaussians
from gsw.scenes import frustum_scene


def cuda_time(fn: Callable[[], object], reps: int, warmup: int,
              before: Callable[[], None] | None = None) -> tuple[float, list[float]]:
    """Median milliseconds of `fn` over `reps` runs (CUDA events), after `warmup` runs."""
    for _ in range(warmup):
        if before:
            before()
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(reps):
        if before:
            before()
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        fn()
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end))
    return statistics.median(times), times


def peak_mb(fn: Callable[[], object], before: Callable[[], None] | None = None) -> float:
    if before:
        before()
    torch.cuda.synchronize()
    base = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    out = fn()
    torch.cuda.synchronize()
    peak = torch.cuda.max_memory_allocated()
    del out
    return (peak - base) / 2**20


def env_info() -> dict[str, object]:
    info: dict[str, object] = dict(
        gpu=torch.cuda.get_device_name(), torch=torch.__version__, cuda=torch.version.cuda,
        python=platform.python_version(), gsw_build=gsw.build_info(),
        date=time.strftime("%Y-%m-%d %H:%M:%S %Z"))
    try:
        info["driver"] = subprocess.run(
            ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
            capture_output=True, text=True, timeout=30).stdout.strip()
    except Exception as e:  # noqa: BLE001
        info["driver"] = f"unknown ({e})"
    return info


def bench_config(n: int, width: int, height: int, reps: int, warmup: int, use_gsplat: bool,
                 breakdown: bool) -> dict[str, object]:
    cam = Camera.from_fov(0.8, width, height)
    g = frustum_scene(n, cam, sh_degree=3, seed=0, device="cuda")
    gen = torch.Generator(device="cpu").manual_seed(1)
    w_img = torch.rand(3, height, width, generator=gen).cuda()
    w_contrib = torch.rand(3, height, width, generator=gen).cuda()
    row: dict[str, object] = dict(N=n, width=width, height=height)

    # ---------------------------------------------------------------- gsw
    def gsw_fwd():
        with torch.no_grad():
            return gsw.rasterize(g, cam, validate=False).image

    params = [t.detach().clone().requires_grad_() for t in
              (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh)]
    g_train = Gaussians(*params)

    def reset_gsw():
        for p in params:
            p.grad = None

    def gsw_fwdbwd():
        out = gsw.rasterize(g_train, cam, validate=False)
        (out.image * w_img).sum().backward()
        return params[0].grad

    def gsw_contrib():
        return gsw.contribution(g, cam, w_contrib).values

    out = gsw.rasterize(g, cam)
    row["intersections"] = int(out.bins.num_intersections)
    row["visible"] = int(out.visible.sum())
    row["gsw_fwd_ms"], _ = cuda_time(gsw_fwd, reps, warmup)
    row["gsw_fwdbwd_ms"], _ = cuda_time(gsw_fwdbwd, reps, warmup, reset_gsw)
    row["gsw_contrib_ms"], _ = cuda_time(gsw_contrib, reps, warmup)
    row["gsw_fwd_peak_mb"] = peak_mb(gsw_fwd)
    row["gsw_fwdbwd_peak_mb"] = peak_mb(gsw_fwdbwd, reset_gsw)
    row["gsw_contrib_peak_mb"] = peak_mb(gsw_contrib)
    row["contrib_over_fwd"] = row["gsw_contrib_ms"] / row["gsw_fwd_ms"]
    gsw_image = gsw_fwd()
    reset_gsw()

    if breakdown:
        row["gsw_breakdown_ms"] = stage_breakdown(g, cam, w_img, reps, warmup)

    # ---------------------------------------------------------------- gsplat
    if use_gsplat:
        import gsplat

        scales = g.log_scales.exp().contiguous()
        opac = torch.sigmoid(g.opacity_logits).contiguous()
        viewmats = cam.viewmat.float().cuda()[None]
        Ks = cam.K.float().cuda()[None]

        def gs_fwd():
            with torch.no_grad():
                return gsplat.rasterization(g.means, g.quats, scales, opac, g.sh, viewmats, Ks,
                                            width, height, sh_degree=3)[0]

        gp = [t.detach().clone().requires_grad_() for t in (g.means, g.quats, scales, opac, g.sh)]
        w_hwc = w_img.permute(1, 2, 0)[None].contiguous()

        def reset_gs():
            for p in gp:
                p.grad = None

        def gs_fwdbwd():
            img = gsplat.rasterization(*gp, viewmats, Ks, width, height, sh_degree=3)[0]
            (img * w_hwc).sum().backward()
            return gp[0].grad

        row["gsplat_fwd_ms"], _ = cuda_time(gs_fwd, reps, warmup)
        row["gsplat_fwdbwd_ms"], _ = cuda_time(gs_fwdbwd, reps, warmup, reset_gs)
        row["gsplat_fwd_peak_mb"] = peak_mb(gs_fwd)
        row["gsplat_fwdbwd_peak_mb"] = peak_mb(gs_fwdbwd, reset_gs)
        gs_image = gs_fwd()[0].permute(2, 0, 1)
        diff = (gs_image - gsw_image).abs()
        row["image_mean_abs_diff_vs_gsplat"] = float(diff.mean())
        row["image_max_abs_diff_vs_gsplat"] = float(diff.max())
        row["fwd_ratio"] = row["gsw_fwd_ms"] / row["gsplat_fwd_ms"]
        row["fwdbwd_ratio"] = row["gsw_fwdbwd_ms"] / row["gsplat_fwdbwd_ms"]
        row["fwdbwd_peak_ratio"] = row["gsw_fwdbwd_peak_mb"] / row["gsplat_fwdbwd_peak_mb"]
        row["fwd_peak_ratio"] = row["gsw_fwd_peak_mb"] / row["gsplat_fwd_peak_mb"]
        del gp, scales, opac
    del g, params, g_train
    torch.cuda.empty_cache()
    return row


def stage_breakdown(g: Gaussians, cam: Camera, w_img: torch.Tensor, reps: int, warmup: int) -> dict[str, float]:
    """Median ms of each op of the gsw pipeline (forward and backward), timed separately."""
    from gsw import _C
    from gsw.render.rasterize import _camera_args

    ca = _camera_args(cam)
    W, H = cam.width, cam.height
    ins = (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)
    radii, m2d, conics, depths, colors, opac = _C.project_forward(*ins, sh_degree=3, **ca)
    bins = _C.bin_gaussians(m2d, radii, depths, W, H)
    bg = torch.zeros(3, device="cuda")
    image, alpha, depth, final_T, n_contrib = _C.rasterize_forward(m2d, conics, colors, opac, depths, bg,
                                                                    bins=bins, width=W, height=H)
    v_img = w_img.contiguous()
    v_a, v_d = torch.zeros_like(alpha), torch.zeros_like(depth)
    grads = _C.rasterize_backward(m2d, conics, colors, opac, depths, bg, bins=bins, width=W, height=H,
                                  final_T=final_T, n_contrib=n_contrib, v_image=v_img, v_alpha=v_a, v_depth=v_d)
    stages = {
        "project_fwd": lambda: _C.project_forward(*ins, sh_degree=3, **ca),
        "bin": lambda: _C.bin_gaussians(m2d, radii, depths, W, H),
        "blend_fwd": lambda: _C.rasterize_forward(m2d, conics, colors, opac, depths, bg, bins=bins,
                                                  width=W, height=H),
        "blend_bwd": lambda: _C.rasterize_backward(m2d, conics, colors, opac, depths, bg, bins=bins, width=W,
                                                   height=H, final_T=final_T, n_contrib=n_contrib,
                                                   v_image=v_img, v_alpha=v_a, v_depth=v_d),
        "project_bwd": lambda: _C.project_backward(*ins, sh_degree=3, **ca, radii=radii, conics=conics,
                                                   colors=colors, opacities=opac, v_means2d=grads[0],
                                                   v_conics=grads[1], v_depths=grads[4],
                                                   v_colors=grads[2], v_opacities=grads[3]),
        "contribution_kernel": lambda: _C.contribution(m2d, conics, opac, bins=bins, width=W, height=H,
                                                       weights=v_img),
    }
    return {k: cuda_time(f, reps, warmup)[0] for k, f in stages.items()}


def to_markdown(env: dict[str, object], rows: list[dict[str, object]], reps: int, warmup: int) -> str:
    b = env["gsw_build"]
    lines = [
        "# gsw CUDA rasterizer " + ("vs gsplat 1.5.3" if any("gsplat_fwd_ms" in r for r in rows)
                                     else "(gsplat not run: its columns are empty)"),
        "",
        f"GPU: {env['gpu']} (driver {env['driver']}); torch {env['torch']}, CUDA {env['cuda']}, "
        f"Python {env['python']}; gsw CUDA archs {b.get('cuda_archs')}; {env['date']}.",
        "",
        "Scene: `frustum_scene(N, Camera.from_fov(0.8, W, H), sh_degree=3, seed=0)`, float32. "
        f"Median of {reps} runs after {warmup} warm-up runs, CUDA events, whole pipeline "
        "(projection + SH, binning/sort, blending; backward through everything). "
        "Peak = extra GPU memory during one run (MiB). Ratio = gsw / gsplat (< 1: gsw faster).",
        "",
        "| N | size | M | gsw fwd | gsplat fwd | ratio | gsw fwd+bwd | gsplat fwd+bwd | ratio | "
        "gsw contrib | contrib / fwd | peak fwd+bwd gsw / gsplat | peak fwd gsw / gsplat |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        gs = "gsplat_fwd_ms" in r
        f = lambda k, fmt="{:.2f}": fmt.format(r[k]) if k in r else "-"  # noqa: E731
        lines.append(
            f"| {r['N']:,} | {r['width']}x{r['height']} | {r['intersections']:,} | {f('gsw_fwd_ms')} | "
            f"{f('gsplat_fwd_ms')} | {f('fwd_ratio')} | {f('gsw_fwdbwd_ms')} | {f('gsplat_fwdbwd_ms')} | "
            f"**{f('fwdbwd_ratio')}** | {f('gsw_contrib_ms')} | {f('contrib_over_fwd')} | "
            f"{f('gsw_fwdbwd_peak_mb', '{:.0f}')} / {f('gsplat_fwdbwd_peak_mb', '{:.0f}') if gs else '-'} | "
            f"{f('gsw_fwd_peak_mb', '{:.0f}')} / {f('gsplat_fwd_peak_mb', '{:.0f}') if gs else '-'} |")
    bd = [r for r in rows if "gsw_breakdown_ms" in r]
    if bd:
        lines += ["", "gsw stage breakdown (ms, each op timed alone):", ""]
        keys = list(bd[0]["gsw_breakdown_ms"])
        lines.append("| N | size | " + " | ".join(keys) + " |")
        lines.append("|---|---|" + "---|" * len(keys))
        for r in bd:
            lines.append(f"| {r['N']:,} | {r['width']}x{r['height']} | " +
                         " | ".join(f"{r['gsw_breakdown_ms'][k]:.3f}" for k in keys) + " |")
    if any("image_mean_abs_diff_vs_gsplat" in r for r in rows):
        lines += ["", "Image difference gsw vs gsplat (mean / max abs): " + "; ".join(
            f"{r['N']:,}@{r['width']}x{r['height']}: {r['image_mean_abs_diff_vs_gsplat']:.1e} / "
            f"{r['image_max_abs_diff_vs_gsplat']:.1e}" for r in rows if "image_mean_abs_diff_vs_gsplat" in r)
            + " (gsplat clamps alpha at 0.999 and sizes footprints differently; gsw follows INRIA)."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ns", type=int, nargs="+", default=[100_000, 1_000_000, 3_000_000])
    ap.add_argument("--sizes", nargs="+", default=["800x800", "1920x1080"])
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--no-gsplat", action="store_true")
    ap.add_argument("--breakdown", action="store_true", help="also time each gsw op alone")
    ap.add_argument("--out", default="benchmarks/results/cuda.json")
    ap.add_argument("--md", default="benchmarks/results/cuda.md")
    args = ap.parse_args()
    assert torch.cuda.is_available() and gsw.build_info()["cuda"], "needs a GPU and a CUDA build of gsw"
    env = env_info()
    print(env, flush=True)
    rows = []
    for size in args.sizes:
        w, h = (int(v) for v in size.split("x"))
        for n in args.ns:
            row = bench_config(n, w, h, args.reps, args.warmup, not args.no_gsplat, args.breakdown)
            print(json.dumps(row), flush=True)
            rows.append(row)
    with open(args.out, "w") as f:
        json.dump(dict(env=env, reps=args.reps, warmup=args.warmup, rows=rows), f, indent=1)
    md = to_markdown(env, rows, args.reps, args.warmup)
    with open(args.md, "w") as f:
        f.write(md)
    print(md)


if __name__ == "__main__":
    main()
