"""gsw CUDA rasterizer vs gsplat 1.5.3 (both of its modes), side by side on identical scenes (one GPU, one run).

Scene families (float32 on the GPU, SH degree 3):

* ``frustum``: `gsw.scenes.frustum_scene(N, Camera.from_fov(0.8, W, H), seed=0)` (coverage 4, opacity logits
  N(0, 1)), the light family;
* ``heavy``: `gsw.scenes.heavy_scene(N, Camera.from_fov(radians(60), W, H), seed=0)` (depth uniform 2-12, world
  scale exp(N(-4.6, 0.5)) x 0.5 x depth, opacity logits N(0, 2), DC uniform in [-1, 1]);
* ``ply``: a trained model read from `--ply` (e.g. ../shared/data/ply/sh3_fixture/point_cloud.ply), seen from
  2.5 times its 90 % radius (60 degree field of view, z up).

Timed (CUDA events, median of `--reps` after `--warmup` untimed runs), whole pipeline from the raw Gaussian
tensors to the image:

* forward: `gsw.rasterize` / `gsplat.rasterization` under `torch.no_grad()`; gsw with `validate=False`, with
  `validate=True` (the default: a device-side NaN/Inf flag, no extra synchronisation) and with the host check
  `Gaussians.check_finite()` that `validate=True` did before (one synchronisation per field);
* forward+backward: the same with gradients, loss = sum(image * fixed random weights), `loss.backward()`
  (gradients reset before each run, outside the timed region);
* contribution (gsw only): `gsw.contribution(g, cam, weights[3, H, W])`, reported against gsw's forward.

gsw's and gsplat's forward and forward+backward are timed in `--rounds` alternating rounds (gsw, gsplat packed,
gsplat unpacked, each forward then forward+backward), and each is reported as the median of its rounds: a drift of
the GPU's or the host's speed over a case's run falls on both renderers alike.

gsplat runs with `packed=True` (its default) and `packed=False`; each gsw time is compared with the faster
mode of that measurement. gsplat gets pre-activated scales/opacities (its API takes them; the activation is
not timed) and default settings otherwise (16x16 tiles, eps2d 0.3 as ours). Peak memory is
`torch.cuda.max_memory_allocated()` during one run minus what was allocated before it; a forward+backward keeps
the rendered image alone, for both renderers (gsw's alpha, depth and bins, gsplat's alphas and meta are dropped
before the backward). gsw's blend backward holds at most its records budget at once (`GSW_BLEND_RECORDS_MIB`,
csrc/core/params.h: by default `kRecordsBudgetMiB`, 256 MiB, of csrc/core/constants.h; 0 for no limit;
`records_budget.py` measures the trade-off).

`--breakdown` also times each gsw op alone, with the ellipse tile assignment (csrc/core/tiles.h) and with every
tile of the radius rectangles (`_rect`: the rule before it, on the same splats), which is the before/after of
that change.

`--backward atomic auto cut px2 px4` compares the CUDA blend backward's variants (the benchmarking switch
GSW_CUDA_BACKWARD of csrc/cuda/rasterize_cuda.cu, set in this process around each call): per variant the
blend backward op alone on the same bins and the whole forward+backward, two interleaved rounds, and the
largest gradient difference to the first variant named (relative to each gradient tensor's largest value).

`--contribution auto px4 px2` times the contribution's layouts (GSW_CUDA_CONTRIBUTION) alike, two interleaved
rounds each, with the largest difference of the values to the first variant named.

    python benchmarks/bench_cuda.py --out benchmarks/results/cuda.json --md benchmarks/results/cuda.md
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import statistics
import subprocess
import time
from typing import Callable

import torch

import gsw
from gsw.camera import Camera
from gsw.gaussians import Gaussians
from gsw.scenes import frustum_scene, heavy_scene

GSPLAT_MODES = {"packed": True, "unpacked": False}
BACKWARD_ENV = "GSW_CUDA_BACKWARD"  # read by the CUDA blend backward at every call
BACKWARD_VARIANTS = ("atomic", "auto", "cut", "px2", "px4")
CONTRIBUTION_ENV = "GSW_CUDA_CONTRIBUTION"  # read by the CUDA contribution at every call
CONTRIBUTION_VARIANTS = ("auto", "px2", "px4")


def cuda_time(fn: Callable[[], object], reps: int, warmup: int,
              before: Callable[[], None] | None = None) -> float:
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
    return statistics.median(times)


def peak_mb(fn: Callable[[], object], before: Callable[[], None] | None = None) -> float:
    """Extra GPU memory (MiB) allocated at the peak of one run of `fn`."""
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


def env_info(commit: str) -> dict[str, object]:
    info: dict[str, object] = dict(
        gpu=torch.cuda.get_device_name(), torch=torch.__version__, cuda=torch.version.cuda,
        python=platform.python_version(), gsw_build=gsw.build_info(), gsw_commit=commit,
        date=time.strftime("%Y-%m-%d %H:%M:%S %Z"))
    try:
        import gsplat

        info["gsplat"] = gsplat.__version__
    except ImportError:
        info["gsplat"] = None
    try:
        info["driver"] = subprocess.run(
            ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
            capture_output=True, text=True, timeout=30).stdout.strip()
    except Exception as e:  # noqa: BLE001
        info["driver"] = f"unknown ({e})"
    return info


def ply_camera(g: Gaussians, width: int, height: int) -> Camera:
    """A 60-degree camera 2.5 radii (90 % quantile) from the model's median point, slightly above it, z up."""
    m = g.means.detach().float().cpu()
    centre = m.median(0).values
    r = float((m - centre).norm(dim=1).quantile(0.9))
    eye = centre + torch.tensor([0.0, -2.5 * r, 0.5 * r])
    return Camera.look_at(tuple(eye.tolist()), tuple(centre.tolist()), (0.0, 0.0, 1.0), math.radians(60), width, height)


def make_scene(family: str, n: int, width: int, height: int, ply: str | None,
               device: str = "cuda") -> tuple[Gaussians, Camera]:
    if family == "frustum":
        cam = Camera.from_fov(0.8, width, height)
        return frustum_scene(n, cam, sh_degree=3, seed=0, device=device), cam
    if family == "heavy":
        cam = Camera.from_fov(math.radians(60), width, height)
        return heavy_scene(n, cam, sh_degree=3, seed=0, device=device), cam
    if family == "ply":
        from gsw.io.ply import load_ply

        g = load_ply(ply)
        return g.to(device), ply_camera(g, width, height)
    raise ValueError(f"unknown scene family {family!r}")


def parse_case(case: str) -> tuple[str, int, int, int]:
    """A case "family:N:WxH" as (family, N, W, H)."""
    family, n, size = case.split(":")
    w, h = (int(v) for v in size.split("x"))
    return family, int(n), w, h


def trainable(g: Gaussians) -> tuple[list[torch.Tensor], Gaussians]:
    """Leaf copies of g's parameters (means, log_scales, quats, opacity_logits, sh) and the Gaussians over them."""
    params = [t.detach().clone().requires_grad_() for t in (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh)]
    return params, Gaussians(*params)


def fwdbwd_pair(g: Gaussians, cam: Camera, w_img: torch.Tensor, keep_image: bool = True):
    """One forward+backward of gsw and of gsplat 1.5.3 (`packed=False`) on a scene, loss = sum(image * w_img), as
    ((gsw_fn, gsw_reset), (gsplat_fn, gsplat_reset)) (gsw_ops / gsplat_ops; reset: the gradients to None)."""
    _, gsw_fwdbwd, gsw_reset = gsw_ops(g, cam, w_img, keep_image)
    _, gsplat_fwdbwd, gsplat_reset = gsplat_ops(g, cam, w_img, False, keep_image)
    return (gsw_fwdbwd, gsw_reset), (gsplat_fwdbwd, gsplat_reset)


def gsw_ops(g: Gaussians, cam: Camera, w_img: torch.Tensor, keep_image: bool = True):
    """gsw's forward (no grad; `validate`, `host_check`: the device flag, the former host check) and
    forward+backward (loss = sum(image * w_img); with `keep_image` the image alone is kept alive through the
    backward and returned, as a training loop does and as gsplat_ops does with gsplat's: the other outputs are
    freed before the backward, except what the backward itself saved; without it the image is a temporary, freed
    once the loss's product is made), and the reset of its gradients, as (fwd, fwdbwd, reset)."""
    def fwd(validate: bool = False, host_check: bool = False):
        with torch.no_grad():
            if host_check:
                g.check_finite()
            return gsw.rasterize(g, cam, validate=validate).image

    params, g_train = trainable(g)

    def fwdbwd(validate: bool = False):
        if not keep_image:
            (gsw.rasterize(g_train, cam, validate=validate).image * w_img).sum().backward()
            return None
        image = gsw.rasterize(g_train, cam, validate=validate).image
        (image * w_img).sum().backward()
        return image

    def reset():
        for p in params:
            p.grad = None

    return fwd, fwdbwd, reset


def bench_gsw(g: Gaussians, cam: Camera, w_img: torch.Tensor, w_contrib: torch.Tensor, reps: int,
              warmup: int) -> tuple[dict[str, float], torch.Tensor]:
    """gsw's validation and contribution timings and its peaks for one scene; returns them and the forward
    image (the forward and forward+backward against gsplat's: head_to_head)."""
    fwd, fwdbwd, reset = gsw_ops(g, cam, w_img)

    def contrib():
        return gsw.contribution(g, cam, w_contrib).values

    r: dict[str, float] = {}
    # validate=True against validate=False, two interleaved measurements of each (the spread of one measurement);
    # the plain forward and forward+backward against gsplat's are timed in head_to_head's rounds
    r["gsw_fwd_plain_ms"] = cuda_time(fwd, reps, warmup)
    r["gsw_fwd_validate_ms"] = cuda_time(lambda: fwd(True), reps, warmup)
    r["gsw_fwd_hostcheck_ms"] = cuda_time(lambda: fwd(False, True), reps, warmup)
    r["gsw_fwd_plain_ms_again"] = cuda_time(fwd, reps, warmup)
    r["gsw_fwd_validate_ms_again"] = cuda_time(lambda: fwd(True), reps, warmup)
    r["gsw_fwdbwd_validate_ms"] = cuda_time(lambda: fwdbwd(True), reps, warmup, reset)
    r["gsw_contrib_ms"] = cuda_time(contrib, reps, warmup)
    r["gsw_fwd_peak_mb"] = peak_mb(fwd)
    r["gsw_fwdbwd_peak_mb"] = peak_mb(fwdbwd, reset)
    r["gsw_contrib_peak_mb"] = peak_mb(contrib)
    image = fwd()
    reset()
    return r, image


def gsplat_inputs(g: Gaussians, cam: Camera, w_img: torch.Tensor):
    """gsplat's inputs for a scene: activated scales and opacities (its API takes them; not timed), leaf copies of
    (means, quats, scales, opacities, sh) for its backward, viewmats [1, 4, 4], Ks [1, 3, 3] and the loss weights
    as [1, H, W, 3]."""
    scales = g.log_scales.exp().contiguous()
    opac = torch.sigmoid(g.opacity_logits).contiguous()
    gp = [t.detach().clone().requires_grad_() for t in (g.means, g.quats, scales, opac, g.sh)]
    viewmats = cam.viewmat.float().to(g.means.device)[None]
    Ks = cam.K.float().to(g.means.device)[None]
    return scales, opac, gp, viewmats, Ks, w_img.permute(1, 2, 0)[None].contiguous()


def gsplat_ops(g: Gaussians, cam: Camera, w_img: torch.Tensor, packed: bool, keep_image: bool = True):
    """gsplat 1.5.3's forward (no grad) and forward+backward in one mode (`keep_image` as in gsw_ops), and the
    reset of its gradients, as (fwd, fwdbwd, reset)."""
    import gsplat

    scales, opac, gp, viewmats, Ks, w_hwc = gsplat_inputs(g, cam, w_img)
    W, H = cam.width, cam.height

    def fwd():
        with torch.no_grad():
            return gsplat.rasterization(g.means, g.quats, scales, opac, g.sh, viewmats, Ks, W, H, sh_degree=3,
                                        packed=packed)[0]

    def fwdbwd():
        if not keep_image:
            (gsplat.rasterization(*gp, viewmats, Ks, W, H, sh_degree=3, packed=packed)[0] * w_hwc).sum().backward()
            return None
        img = gsplat.rasterization(*gp, viewmats, Ks, W, H, sh_degree=3, packed=packed)[0]
        (img * w_hwc).sum().backward()
        return img

    def reset():
        for p in gp:
            p.grad = None

    return fwd, fwdbwd, reset


def bench_gsplat(g: Gaussians, cam: Camera, w_img: torch.Tensor, gsw_image: torch.Tensor) -> dict[str, float]:
    """gsplat 1.5.3's peaks in both modes, and its image difference to gsw's (its times: head_to_head)."""
    r: dict[str, float] = {}
    for mode, packed in GSPLAT_MODES.items():
        fwd, fwdbwd, reset = gsplat_ops(g, cam, w_img, packed)
        r[f"gsplat_{mode}_fwd_peak_mb"] = peak_mb(fwd)
        r[f"gsplat_{mode}_fwdbwd_peak_mb"] = peak_mb(fwdbwd, reset)
        diff = (fwd()[0].permute(2, 0, 1) - gsw_image).abs()
        r[f"image_mean_abs_diff_vs_gsplat_{mode}"] = float(diff.mean())
        r[f"image_max_abs_diff_vs_gsplat_{mode}"] = float(diff.max())
        reset()
    return r


def head_to_head(g: Gaussians, cam: Camera, w_img: torch.Tensor, reps: int, warmup: int, rounds: int,
                 with_gsplat: bool) -> dict[str, object]:
    """gsw's and gsplat's forward and forward+backward, timed in `rounds` alternating rounds (each round: gsw,
    then gsplat packed, then unpacked, forward then forward+backward): each time is the median of its rounds'
    medians, so a drift of the GPU or the host over the case's run falls on both renderers alike."""
    ops = {"gsw": gsw_ops(g, cam, w_img)}
    if with_gsplat:
        ops.update({f"gsplat_{mode}": gsplat_ops(g, cam, w_img, packed) for mode, packed in GSPLAT_MODES.items()})
    times: dict[str, list[float]] = {f"{name}_{k}": [] for name in ops for k in ("fwd_ms", "fwdbwd_ms")}
    for _ in range(rounds):
        for name, (fwd, fwdbwd, reset) in ops.items():
            times[f"{name}_fwd_ms"].append(cuda_time(fwd, reps, warmup))
            times[f"{name}_fwdbwd_ms"].append(cuda_time(fwdbwd, reps, warmup, reset))
            reset()
    r: dict[str, object] = {k: statistics.median(v) for k, v in times.items()}
    r.update({f"{k}_rounds": v for k, v in times.items()})
    return r


def compare(row: dict[str, object]) -> None:
    """Adds each measurement's faster gsplat mode and gsw's ratio to it (< 1: gsw faster / smaller)."""
    for key in ("fwd_ms", "fwdbwd_ms", "fwd_peak_mb", "fwdbwd_peak_mb"):
        modes = [m for m in GSPLAT_MODES if f"gsplat_{m}_{key}" in row]
        if not modes:
            continue
        best = min(modes, key=lambda m: row[f"gsplat_{m}_{key}"])
        row[f"gsplat_best_{key}_mode"] = best
        row[f"ratio_{key}"] = row[f"gsw_{key}"] / row[f"gsplat_{best}_{key}"]


@contextlib.contextmanager
def env_setting(name: str, value: str | None):
    """Runs the block with environment variable `name` set to `value` (None: unset), restoring it after (the
    kernels' benchmarking switches are read at every call)."""
    old = os.environ.get(name)
    if value is None:
        os.environ.pop(name, None)
    else:
        os.environ[name] = value
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = old


def backward_variant(name: str | None):
    """Runs the block with the CUDA blend backward `name` (None: the default)."""
    return env_setting(BACKWARD_ENV, name)


def compare_backward_variants(g: Gaussians, cam: Camera, w_img: torch.Tensor, variants: list[str], reps: int,
                              warmup: int) -> dict[str, float]:
    """Blend backward op alone and whole forward+backward per backward variant (two interleaved rounds, ms), and
    each variant's largest gradient difference to the first variant's (relative to each tensor's max abs)."""
    from gsw import _C
    from gsw.render.rasterize import _camera_args

    ca = _camera_args(cam)
    W, H = cam.width, cam.height
    ins = (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)
    radii, m2d, conics, depths, colors, opac = _C.project_forward(*ins, sh_degree=3, **ca)
    bins = _C.bin_gaussians(m2d, conics, opac, radii, depths, W, H)
    bg = torch.zeros(3, device=g.means.device)
    _, _, _, final_T, n_contrib = _C.rasterize_forward(m2d, conics, colors, opac, depths, bg, bins=bins, width=W,
                                                       height=H)
    bwd = lambda: _C.rasterize_backward(m2d, conics, colors, opac, depths, bg, bins=bins,  # noqa: E731
                                        width=W, height=H, final_T=final_T, n_contrib=n_contrib, v_image=w_img)
    params, g_train = trainable(g)

    def reset():
        for p in params:
            p.grad = None

    def fwdbwd():
        (gsw.rasterize(g_train, cam, validate=False).image * w_img).sum().backward()

    res: dict[str, float] = {}
    for rnd in range(2):
        for v in variants:
            with backward_variant(v):
                res[f"blend_bwd_{v}_{rnd}"] = cuda_time(bwd, reps, warmup)
                res[f"fwdbwd_{v}_{rnd}"] = cuda_time(fwdbwd, reps, warmup, reset)
    for v in variants:
        for key in ("blend_bwd", "fwdbwd"):
            res[f"{key}_{v}"] = (res[f"{key}_{v}_0"] + res[f"{key}_{v}_1"]) / 2
    ref = None
    for v in variants:
        with backward_variant(v):
            grads = [t.clone() for t in bwd()]
            res[f"fwdbwd_peak_mb_{v}"] = peak_mb(fwdbwd, reset)
            # the same bins and cotangents again: do the gradients come back as the same bits?
            res[f"bitwise_repeats_{v}"] = sum(all(torch.equal(a, b) for a, b in zip(bwd(), grads)) for _ in range(5))
        if ref is None:
            ref = grads
        res[f"grad_maxdiff_{v}"] = max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-30))
                                       for a, b in zip(grads, ref) if b.numel())
    reset()
    return res


def compare_contribution_variants(g: Gaussians, cam: Camera, w_contrib: torch.Tensor, variants: list[str], reps: int,
                                  warmup: int) -> dict[str, float]:
    """The contribution per layout (two interleaved rounds, ms) and each one's largest difference of the values to
    the first variant's (relative to their max abs)."""
    def contrib():
        return gsw.contribution(g, cam, w_contrib).values

    res: dict[str, float] = {}
    for rnd in range(2):
        for v in variants:
            with env_setting(CONTRIBUTION_ENV, v):
                res[f"contrib_{v}_{rnd}"] = cuda_time(contrib, reps, warmup)
    ref = None
    for v in variants:
        res[f"contrib_{v}"] = (res[f"contrib_{v}_0"] + res[f"contrib_{v}_1"]) / 2
        with env_setting(CONTRIBUTION_ENV, v):
            values = contrib()
        ref = values if ref is None else ref
        res[f"contrib_maxdiff_{v}"] = float((values - ref).abs().max() / ref.abs().max().clamp_min(1e-30))
    return res


def bench_case(family: str, n: int, width: int, height: int, args: argparse.Namespace) -> dict[str, object]:
    g, cam = make_scene(family, n, width, height, args.ply, args.device)
    gen = torch.Generator(device="cpu").manual_seed(1)
    w_img = torch.rand(3, height, width, generator=gen).to(args.device)
    w_contrib = torch.rand(3, height, width, generator=gen).to(args.device)
    out = gsw.rasterize(g, cam)
    row: dict[str, object] = dict(family=family, N=len(g), width=width, height=height,
                                  intersections=int(out.bins.num_intersections), visible=int(out.visible.sum()),
                                  alpha_mean=float(out.alpha.mean()))
    del out
    timings, image = bench_gsw(g, cam, w_img, w_contrib, args.reps, args.warmup)
    row.update(timings)
    # two interleaved measurements of each (fwd, +val, host, fwd, +val)
    row["validate_overhead"] = ((row["gsw_fwd_validate_ms"] + row["gsw_fwd_validate_ms_again"])
                                / (row["gsw_fwd_plain_ms"] + row["gsw_fwd_plain_ms_again"]) - 1)
    row["contrib_over_fwd"] = row["gsw_contrib_ms"] / row["gsw_fwd_plain_ms"]  # the forward timed beside it
    if args.breakdown:
        row["gsw_breakdown_ms"] = stage_breakdown(g, cam, w_img, args.reps, args.warmup)
    if args.backward:
        row["gsw_backward_variants"] = compare_backward_variants(g, cam, w_img, args.backward, args.reps,
                                                                 args.warmup)
    if args.contribution:
        row["gsw_contribution_variants"] = compare_contribution_variants(g, cam, w_contrib, args.contribution,
                                                                         args.reps, args.warmup)
    if not args.no_gsplat:
        row.update(bench_gsplat(g, cam, w_img, image))
    row.update(head_to_head(g, cam, w_img, args.reps, args.warmup, args.rounds, not args.no_gsplat))
    if not args.no_gsplat:
        compare(row)
    del g, image
    torch.cuda.empty_cache()
    return row


def stage_breakdown(g: Gaussians, cam: Camera, w_img: torch.Tensor, reps: int, warmup: int) -> dict[str, float]:
    """Median ms of each gsw op alone; binning and blending with the ellipse tiles and with the radius rectangles."""
    from gsw import _C
    from gsw.render.rasterize import _camera_args

    ca = _camera_args(cam)
    W, H = cam.width, cam.height
    ins = (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)
    radii, m2d, conics, depths, colors, opac = _C.project_forward(*ins, sh_degree=3, **ca)
    # The tile rule before the ellipse test: every tile of the radius rectangle (zero conics in the binning only
    # make tile_footprint fall back to the rectangle; the blending gets the real conics).
    rect_conics = torch.zeros_like(conics)
    bg = torch.zeros(3, device=g.means.device)
    v_img = w_img.contiguous()
    res: dict[str, float] = {"project_fwd": cuda_time(lambda: _C.project_forward(*ins, sh_degree=3, **ca), reps, warmup)}
    images = {}
    for tag, bin_conics in (("", conics), ("_rect", rect_conics)):
        bins = _C.bin_gaussians(m2d, bin_conics, opac, radii, depths, W, H)
        res["M" + tag] = float(bins.num_intersections)
        image, alpha, depth, final_T, n_contrib = _C.rasterize_forward(m2d, conics, colors, opac, depths, bg,
                                                                        bins=bins, width=W, height=H)
        images[tag] = image
        bwd = lambda: _C.rasterize_backward(m2d, conics, colors, opac, depths, bg, bins=bins,  # noqa: E731
                                            width=W, height=H, final_T=final_T, n_contrib=n_contrib, v_image=v_img)
        res["bin" + tag] = cuda_time(lambda: _C.bin_gaussians(m2d, bin_conics, opac, radii, depths, W, H), reps,
                                     warmup)
        res["blend_fwd" + tag] = cuda_time(lambda: _C.rasterize_forward(m2d, conics, colors, opac, depths, bg,
                                                                         bins=bins, width=W, height=H), reps, warmup)
        res["blend_bwd" + tag] = cuda_time(bwd, reps, warmup)
        res["contribution_kernel" + tag] = cuda_time(
            lambda: _C.contribution(m2d, conics, opac, bins=bins, width=W, height=H, weights=v_img), reps, warmup)
        if not tag:
            grads = bwd()
            res["project_bwd"] = cuda_time(lambda: _C.project_backward(
                *ins, sh_degree=3, **ca, radii=radii, v_means2d=grads[0], v_conics=grads[1], v_depths=grads[4], v_colors=grads[2],
                v_opacities=grads[3]), reps, warmup)
    res["image_max_abs_diff_rect"] = float((images[""] - images["_rect"]).abs().max())
    return res


def _f(r: dict[str, object], key: str, fmt: str = "{:.2f}") -> str:
    return fmt.format(r[key]) if key in r else "-"


def _gsplat_pair(r: dict[str, object], key: str, fmt: str = "{:.2f}") -> str:
    return " / ".join(_f(r, f"gsplat_{m}_{key}", fmt) for m in GSPLAT_MODES)


def to_markdown(env: dict[str, object], rows: list[dict[str, object]], reps: int, warmup: int, rounds: int) -> str:
    b = env["gsw_build"]
    lines = [
        f"# gsw CUDA rasterizer vs gsplat {env.get('gsplat') or '(not run)'} (packed / unpacked)", "",
        f"GPU: {env['gpu']} (driver {env['driver']}); torch {env['torch']}, CUDA {env['cuda']}, "
        f"Python {env['python']}; gsw {env.get('gsw_commit', '?')}, CUDA archs {b.get('cuda_archs')}; {env['date']}.",
        "", f"Median of {reps} runs after {warmup} warm-up runs, CUDA events, ms; fwd and fwd+bwd of gsw and gsplat: "
        f"the median of {rounds} alternating rounds of that. gsw fwd: `validate=False`; "
        "+val: `validate=True` (device flag) and its overhead against `validate=False` (mean of two interleaved "
        "measurements of each); host: the former `check_finite()` + render; contrib/fwd: against the forward timed "
        "beside it. "
        "gsplat: packed / unpacked; ratio = gsw / the faster gsplat mode (named). Peaks: extra MiB.", "",
        "| scene | N | size | M | gsw fwd | +val | val overhead | host check | gsplat fwd | ratio | gsw fwd+bwd "
        "| gsplat fwd+bwd | ratio | contrib | contrib/fwd | peak fwd+bwd gsw / gsplat | peak fwd gsw / gsplat |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['family']} | {r['N']:,} | {r['width']}x{r['height']} | {r['error']} |")
            continue
        mode = lambda k: f" ({r[f'gsplat_best_{k}_mode']})" if f"gsplat_best_{k}_mode" in r else ""  # noqa: E731
        lines.append(
            f"| {r['family']} | {r['N']:,} | {r['width']}x{r['height']} | {r['intersections']:,} | {_f(r, 'gsw_fwd_ms')} | "
            f"{_f(r, 'gsw_fwd_validate_ms')} | {100 * r['validate_overhead']:+.1f} % | {_f(r, 'gsw_fwd_hostcheck_ms')} | "
            f"{_gsplat_pair(r, 'fwd_ms')} | **{_f(r, 'ratio_fwd_ms')}**{mode('fwd_ms')} | {_f(r, 'gsw_fwdbwd_ms')} | "
            f"{_gsplat_pair(r, 'fwdbwd_ms')} | **{_f(r, 'ratio_fwdbwd_ms')}**{mode('fwdbwd_ms')} | "
            f"{_f(r, 'gsw_contrib_ms')} | {_f(r, 'contrib_over_fwd')} | {_f(r, 'gsw_fwdbwd_peak_mb', '{:.0f}')} / "
            f"{_gsplat_pair(r, 'fwdbwd_peak_mb', '{:.0f}')} | {_f(r, 'gsw_fwd_peak_mb', '{:.0f}')} / "
            f"{_gsplat_pair(r, 'fwd_peak_mb', '{:.0f}')} |")
    bd = [r for r in rows if "gsw_breakdown_ms" in r]
    if bd:
        keys = list(bd[0]["gsw_breakdown_ms"])
        lines += ["", "gsw ops alone (ms; M = intersections; `_rect`: the same splats binned to every tile of their "
                  "radius rectangles, i.e. before the ellipse tile assignment):", "",
                  "| scene | N | size | " + " | ".join(keys) + " |", "|---|---|---|" + "---|" * len(keys)]
        for r in bd:
            vals = [f"{v:,.0f}" if k.startswith("M") else (f"{v:.1e}" if k.startswith("image") else f"{v:.3f}")
                    for k, v in r["gsw_breakdown_ms"].items()]
            lines.append(f"| {r['family']} | {r['N']:,} | {r['width']}x{r['height']} | " + " | ".join(vals) + " |")
    bv = [r for r in rows if "gsw_backward_variants" in r]
    if bv:
        names = [k[len("grad_maxdiff_"):] for k in bv[0]["gsw_backward_variants"] if k.startswith("grad_maxdiff_")]
        lines += ["", f"CUDA blend backward variants ({BACKWARD_ENV}; ms, mean of two interleaved rounds; blend bwd: the "
                  "op alone on the same bins; fwd+bwd: the whole pipeline; grad diff: largest gradient difference to "
                  f"{names[0]}, relative to each tensor's max abs; peak: extra MiB of one fwd+bwd; repeats: of 5 more "
                  "blend backwards, those with the same gradient bits):", "",
                  "| scene | N | size | M | " + " | ".join(f"blend bwd {v}" for v in names) + " | "
                  + " | ".join(f"fwd+bwd {v}" for v in names) + " | " + " | ".join(f"grad diff {v}" for v in names[1:])
                  + " | " + " | ".join(f"peak {v}" for v in names) + " | " + " | ".join(f"repeats {v}" for v in names)
                  + " |", "|---|---|---|---|" + "---|" * (5 * len(names) - 1)]
        for r in bv:
            d = r["gsw_backward_variants"]
            lines.append(f"| {r['family']} | {r['N']:,} | {r['width']}x{r['height']} | {r['intersections']:,} | "
                         + " | ".join(f"{d[f'blend_bwd_{v}']:.3f}" for v in names) + " | "
                         + " | ".join(f"{d[f'fwdbwd_{v}']:.2f}" for v in names) + " | "
                         + " | ".join(f"{d[f'grad_maxdiff_{v}']:.1e}" for v in names[1:]) + " | "
                         + " | ".join(f"{d[f'fwdbwd_peak_mb_{v}']:.0f}" for v in names) + " | "
                         + " | ".join(f"{d[f'bitwise_repeats_{v}']}/5" for v in names) + " |")
    cv = [r for r in rows if "gsw_contribution_variants" in r]
    if cv:
        names = [k[len("contrib_maxdiff_"):] for k in cv[0]["gsw_contribution_variants"]
                 if k.startswith("contrib_maxdiff_")]
        lines += ["", f"CUDA contribution layouts ({CONTRIBUTION_ENV}; ms, mean of two interleaved rounds; diff: largest "
                  f"difference of the values to {names[0]}, relative to their max abs):", "",
                  "| scene | N | size | M | " + " | ".join(f"contrib {v}" for v in names) + " | "
                  + " | ".join(f"diff {v}" for v in names[1:]) + " |", "|---|---|---|---|" + "---|" * (2 * len(names) - 1)]
        for r in cv:
            d = r["gsw_contribution_variants"]
            lines.append(f"| {r['family']} | {r['N']:,} | {r['width']}x{r['height']} | {r['intersections']:,} | "
                         + " | ".join(f"{d[f'contrib_{v}']:.3f}" for v in names) + " | "
                         + " | ".join(f"{d[f'contrib_maxdiff_{v}']:.1e}" for v in names[1:]) + " |")
    diffs = [r for r in rows if "image_mean_abs_diff_vs_gsplat_unpacked" in r]
    if diffs:
        lines += ["", "Image difference gsw vs gsplat unpacked (mean / max abs): " + "; ".join(
            f"{r['family']} {r['N']:,}@{r['width']}x{r['height']}: {r['image_mean_abs_diff_vs_gsplat_unpacked']:.1e} / "
            f"{r['image_max_abs_diff_vs_gsplat_unpacked']:.1e}" for r in diffs)
            + " (gsplat clamps alpha at 0.999 and sizes footprints differently; gsw follows INRIA)."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=[f"{f}:{n}:1920x1080" for f in ("frustum", "heavy")
                                                   for n in (100_000, 1_000_000, 3_000_000)],
                    help="family:N:WxH (family frustum, heavy or ply; N is ignored for ply)")
    ap.add_argument("--ply", default="../shared/data/ply/sh3_fixture/point_cloud.ply")
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=3,
                    help="alternating rounds of gsw's and gsplat's forward and forward+backward (median of the rounds)")
    ap.add_argument("--no-gsplat", action="store_true")
    ap.add_argument("--breakdown", action="store_true", help="also time each gsw op alone (ellipse tiles vs radius rectangles)")
    ap.add_argument("--backward", nargs="+", choices=BACKWARD_VARIANTS, default=[],
                    help="also compare these CUDA blend backward variants (the first is the reference of the gradient "
                         "differences), e.g. atomic auto px2 px4")
    ap.add_argument("--contribution", nargs="+", choices=CONTRIBUTION_VARIANTS, default=[],
                    help="also time these CUDA contribution layouts (the first is the reference of the differences)")
    ap.add_argument("--commit", default="", help="gsw commit to record")
    ap.add_argument("--device", default="cuda", help=argparse.SUPPRESS)  # a CPU dry run of the script's logic
    ap.add_argument("--out", default="benchmarks/results/cuda.json")
    ap.add_argument("--md", default="benchmarks/results/cuda.md")
    args = ap.parse_args()
    assert torch.cuda.is_available() and gsw.build_info()["cuda"], "needs a GPU and a CUDA build of gsw"
    env = env_info(args.commit)
    print(env, flush=True)
    rows = []
    for case in args.cases:
        family, n, w, h = parse_case(case)
        try:
            row = bench_case(family, n, w, h, args)
        except torch.cuda.OutOfMemoryError as e:
            row = dict(family=family, N=n, width=w, height=h, error=f"out of memory: {e}"[:200])
            torch.cuda.empty_cache()
        print(json.dumps(row), flush=True)
        rows.append(row)
        with open(args.out, "w") as f:  # after every case, so a cut-off run keeps what it measured
            json.dump(dict(env=env, reps=args.reps, warmup=args.warmup, rounds=args.rounds, rows=rows), f, indent=1)
    md = to_markdown(env, rows, args.reps, args.warmup, args.rounds)
    with open(args.md, "w") as f:
        f.write(md)
    print(md)


if __name__ == "__main__":
    main()
