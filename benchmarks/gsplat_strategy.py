"""gsplat's ``DefaultStrategy`` training lego with ``gsw.rasterization`` swapped in, against gsw's own trainer.

Both runs start from the same random initialisation (``gsw.train.init.random_init``: ``--init-points`` uniform points
in the cameras' box, seed 0), train on NeRF-synthetic lego at 200x200 (white background) for the same number of
steps with the same schedule knobs (densify every 20 steps from step 100 to ``iterations / 2``, opacity reset period
1000, the same SH schedule: ``--sh-schedule``) and are scored by the same function (``gsw.train.evaluate``) on the
held-out views (every 8th view).

* ``gsplat``: a gsplat ``simple_trainer``-style loop: one ``torch.optim.Adam`` per parameter (eps 1e-15; lrs of
  simple_trainer: means 1.6e-4 x scene scale with an exponential decay to 1 %, scales 5e-3, quats 1e-3, opacities
  5e-2, sh0 2.5e-3, shN 2.5e-3 / 20), loss ``0.8 L1 + 0.2 (1 - SSIM)``, ``gsplat.strategy.DefaultStrategy``
  (``refine_start_iter=100``, ``refine_stop_iter=iterations / 2``, ``refine_every=20``, ``reset_every=1000``,
  everything else gsplat's default) reading ``meta["means2d"].grad`` / ``meta["radii"]`` from
  ``gsw.rasterization(..., packed=False)``. DefaultStrategy 1.5.3's own opacity reset never fires, so the loop
  calls gsplat's ``reset_opa`` where gsw's trainer resets (iterations 100 and 1000); ``--no-opacity-resets``
  runs the strategy as shipped (recorded as ``gsplat_as_shipped``).
* ``gsw``: ``gsw.train.train`` (the INRIA recipe) with the same schedule.

SH schedule (``--sh-schedule``, both loops): ``ramp`` (default; gsplat's ``simple_trainer`` and INRIA both ramp):
degree 0 -> 3, +1 every 250 steps; the gsw trainer gets the init truncated to degree 0 (its higher bands are zeros),
from which ``train(init=Gaussians)`` ramps. ``full``: degree 3 from the first step (``train(init=Gaussians)`` of a
degree-3 init starts at its degree).

Each run also records, per refinement, the statistics both densifications decide on (``refines``: Gaussians seen,
quantiles of the mean NDC gradient norm, how many are above the threshold, and how many were duplicated / split /
pruned); the gsw side reads them by wrapping ``_State.densify_and_prune`` for the run.

gsplat is only needed for its pure-Python strategy (its CUDA kernels are never called): put an installed or unpacked
gsplat 1.5.3 on ``PYTHONPATH``. Writes ``benchmarks/results/<tag>.{json,md}``.

Usage:
    GOMP_SPINCOUNT=10000 python benchmarks/gsplat_strategy.py [--iterations 2000] [--which both|gsplat|gsw]
        [--sh-schedule ramp|full] [--tag gsplat_strategy]

``--which gsplat`` and ``--which gsw`` may run as two processes at once (each merges its run into the JSON).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any
from unittest import mock

import torch

import gsw
from gsw._atomic import atomic_write
from gsw.data.loaders import load_nerf_synthetic, scene_extent
from gsw.gaussians import Gaussians
from gsw.metrics.image import ssim
from gsw.train import TrainConfig, train
from gsw.train.densify import _State
from gsw.train.init import init_box, random_init
from gsw.train.loop import evaluate

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "lego"
RESULTS = ROOT / "benchmarks" / "results"


def _gsplat_params(g: Gaussians, extent: float, iterations: int) -> tuple[dict, dict, Any]:
    """simple_trainer's parameter dict, one Adam per parameter and the means' lr scheduler."""
    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(g.means.clone()), "scales": torch.nn.Parameter(g.log_scales.clone()),
        "quats": torch.nn.Parameter(g.quats.clone()), "opacities": torch.nn.Parameter(g.opacity_logits.clone()),
        "sh0": torch.nn.Parameter(g.sh[:, :1].clone()), "shN": torch.nn.Parameter(g.sh[:, 1:].clone())})
    lrs = {"means": 1.6e-4 * extent, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3,
           "shN": 2.5e-3 / 20}
    optimizers = {k: torch.optim.Adam([{"params": params[k], "lr": lr, "name": k}], eps=1e-15)
                  for k, lr in lrs.items()}
    sched = torch.optim.lr_scheduler.ExponentialLR(optimizers["means"], gamma=0.01 ** (1.0 / iterations))
    return params, optimizers, sched


def _grad_stats(grads: torch.Tensor, count: torch.Tensor, threshold: float) -> dict[str, Any]:
    """Summary of the mean NDC gradient norms [N] of the Gaussians seen at least once (count [N] > 0)."""
    seen = grads[count > 0]
    q = torch.quantile(seen.double(), torch.tensor([0.5, 0.9, 0.99], dtype=torch.float64)).tolist() if len(seen) \
        else [0.0, 0.0, 0.0]
    return {"seen": int((count > 0).sum()), "mean_views": float(count[count > 0].float().mean()) if len(seen) else 0.0,
            "grad_p50": q[0], "grad_p90": q[1], "grad_p99": q[2], "above_threshold": int((grads > threshold).sum())}


def _logged_strategy(base: type, records: list[dict[str, Any]]) -> type:
    """``base`` (gsplat's DefaultStrategy) recording, per refinement, its gradient statistics and what it
    duplicated / split / pruned (1-based ``iteration``, as gsw's trainer counts)."""

    class Logged(base):  # type: ignore[misc, valid-type]
        def _grow_gs(self, params, optimizers, state, step):  # noqa: ANN001, ANN202
            grads = state["grad2d"] / state["count"].clamp_min(1)
            rec = {"iteration": step + 1, "n_before": len(params["means"]),
                   **_grad_stats(grads, state["count"], self.grow_grad2d)}
            n_dupli, n_split = super()._grow_gs(params, optimizers, state, step)
            records.append({**rec, "duplicated": int(n_dupli), "split": int(n_split)})
            return n_dupli, n_split

        def _prune_gs(self, params, optimizers, state, step):  # noqa: ANN001, ANN202
            n_prune = super()._prune_gs(params, optimizers, state, step)
            records[-1].update(pruned=int(n_prune), n_after=len(params["means"]))
            return n_prune

    return Logged


def run_gsplat(train_set, test_set, g0: Gaussians, extent: float, args: argparse.Namespace) -> dict[str, Any]:
    """The simple_trainer-style loop with DefaultStrategy on gsw.rasterization (see the module docstring)."""
    from gsplat.strategy import DefaultStrategy  # noqa: PLC0415
    from gsplat.strategy.ops import reset_opa  # noqa: PLC0415

    torch.manual_seed(args.seed)  # the split samples of gsplat's ops come from torch's global generator
    params, optimizers, sched = _gsplat_params(g0, extent, args.iterations)
    refines: list[dict[str, Any]] = []
    strategy = _logged_strategy(DefaultStrategy, refines)(
        refine_start_iter=100, refine_stop_iter=args.iterations // 2, refine_every=20, reset_every=1000,
        verbose=False)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=extent)
    cams, images = list(train_set.cameras), train_set.images
    viewmats = torch.stack([c.viewmat.float() for c in cams])
    Ks = torch.stack([c.K.float() for c in cams])
    bg = torch.ones(1, 3)
    gen = torch.Generator().manual_seed(args.seed)
    order: list[int] = []
    history = []
    t0 = time.perf_counter()
    for step in range(args.iterations):
        if not order:
            order = torch.randperm(len(cams), generator=gen).tolist()
        vi = order.pop()
        sh_degree = min(step // 250, 3) if args.sh_schedule == "ramp" else 3
        colors = torch.cat([params["sh0"], params["shN"]], dim=1)
        renders, _, info = gsw.rasterization(
            params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
            colors, viewmats[vi:vi + 1], Ks[vi:vi + 1], train_set.width, train_set.height, sh_degree=sh_degree,
            backgrounds=bg, packed=False)
        img, gt = renders[0].permute(2, 0, 1), images[vi]
        loss = 0.8 * (img - gt).abs().mean() + 0.2 * (1.0 - ssim(img, gt))
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        sched.step()
        strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        if args.opacity_resets and step < args.iterations // 2 and (step + 1 == 100 or (step + 1) % 1000 == 0):
            # gsw's resets (iterations 100 and 1000, 1-based) with gsplat's own reset_opa and DefaultStrategy's
            # value; DefaultStrategy 1.5.3 never resets by itself (`step % self.reset_every == 0 & step > 0`
            # chains to `... and 0 > 0`).
            reset_opa(params=params, optimizers=optimizers, state=state, value=strategy.prune_opa * 2.0)
        if step % 100 == 0 or step == args.iterations - 1:
            history.append({"step": step, "loss": float(loss.detach()), "num_gaussians": len(params["means"]),
                            "time_s": time.perf_counter() - t0})
            print(f"[gsplat] step {step} loss {float(loss.detach()):.4f} N {len(params['means'])} "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
    train_time = time.perf_counter() - t0
    p = {k: v.detach() for k, v in params.items()}
    final = Gaussians(p["means"], p["scales"], p["quats"], p["opacities"], torch.cat([p["sh0"], p["shN"]], dim=1))
    tm = evaluate(final, list(test_set.cameras), test_set.images, background=(1.0, 1.0, 1.0),
                  names=test_set.names)
    return {"test_psnr": tm["psnr"], "test_ssim": tm["ssim"], "num_gaussians": final.num_gaussians,
            "train_time_s": train_time, "s_per_step": train_time / args.iterations, "history": history,
            "refines": refines, "per_view": tm["per_view"]}


def run_gsw(train_set, test_set, g0: Gaussians, args: argparse.Namespace) -> dict[str, Any]:
    """gsw's own trainer with the same schedule."""
    cfg = TrainConfig(iterations=args.iterations, densify_from_iter=100, densify_until_iter=args.iterations // 2,
                      densification_interval=20, opacity_reset_interval=1000, sh_increase_interval=250,
                      init_points=args.init_points, max_gaussians=None, seed=args.seed, log_interval=100)
    # train(init=Gaussians) starts at the init's SH degree: a degree-0 init (g0's higher bands are zeros) ramps
    # 0 -> 3 every sh_increase_interval like the gsplat loop; a degree-3 init trains degree 3 from the first step.
    init = g0.with_sh_degree(0) if args.sh_schedule == "ramp" else g0
    refines: list[dict[str, Any]] = []
    densify_and_prune = _State.densify_and_prune

    def logged(self: _State, gen: torch.Generator, prune_big: bool) -> dict[str, int]:
        grads = torch.nan_to_num(self.grad_accum / self.denom, nan=0.0, posinf=0.0)
        rec = {"n_before": self.n, **_grad_stats(grads, self.denom, cfg.densify_grad_threshold)}
        out = densify_and_prune(self, gen, prune_big)
        refines.append({"iteration": len(refines) * cfg.densification_interval + cfg.densify_from_iter
                        + cfg.densification_interval, **rec, "duplicated": out["cloned"], "split": out["split"],
                        "pruned": out["pruned"], "n_after": self.n})
        return out

    with mock.patch.object(_State, "densify_and_prune", logged):
        res = train(train_set, config=cfg, init=init, test_set=test_set, progress=False)
    tm = res.test_metrics or {}
    return {"test_psnr": tm["psnr"], "test_ssim": tm["ssim"], "num_gaussians": res.gaussians.num_gaussians,
            "train_time_s": res.train_time_s, "s_per_step": res.train_time_s / res.iterations,
            "history": res.history, "refines": refines, "per_view": tm["per_view"]}


def write_markdown(summary: dict[str, Any], path: Path) -> None:
    """The human-readable report next to the JSON."""
    runs = summary["runs"]
    lines = ["# gsplat DefaultStrategy on gsw.rasterization vs gsw's trainer (lego 200x200, CPU)", "",
             f"{summary['iterations']} steps each, same random init ({summary['init_points']:,} points, seed "
             f"{summary['seed']}), "
             f"{summary['num_test_views']} held-out views, white background, SH schedule "
             f"`{summary['sh_schedule']}` in both loops.", "",
             "| trainer | test PSNR | test SSIM | Gaussians | duplicated / split / pruned (sum) | train time | s/step |",
             "|---|---|---|---|---|---|---|"]
    for name, r in runs.items():
        ref = r.get("refines", [])
        counts = " / ".join(f"{sum(x[k] for x in ref):,}" for k in ("duplicated", "split", "pruned"))
        lines.append(f"| {name} | {r['test_psnr']:.2f} dB | {r['test_ssim']:.4f} | {r['num_gaussians']:,} | "
                     f"{counts} ({len(ref)} refinements) | {r['train_time_s']:.0f} s | {r['s_per_step']:.3f} |")
    if "gsplat" in runs and "gsw" in runs:
        lines += ["", f"PSNR difference (gsplat - gsw): {summary['psnr_diff_db']:+.2f} dB.", "",
                  "Per refinement (every 5th; gsplat's 0-based step + 1): Gaussians before, mean NDC gradient norm "
                  "p50 / p90 / p99, duplicated / split / pruned.", "",
                  "| iteration | gsplat | gsw |", "|---|---|---|"]
        for a, b in list(zip(runs["gsplat"]["refines"], runs["gsw"]["refines"]))[::5]:
            cells = [f"{x['n_before']:,}; {x['grad_p50']:.2e} / {x['grad_p90']:.2e} / {x['grad_p99']:.2e}; "
                     f"{x['duplicated']:,} / {x['split']:,} / {x['pruned']:,}" for x in (a, b)]
            lines.append(f"| {a['iteration']} / {b['iteration']} | {cells[0]} | {cells[1]} |")
    lines += ["", f"Machine: {summary['machine']}. torch {summary['torch']}, gsplat {summary['gsplat']}.",
              f"Command: `{summary['command']}`.", ""]
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--iterations", type=int, default=2000)
    ap.add_argument("--init-points", type=int, default=30_000)
    ap.add_argument("--downscale", type=float, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--which", choices=("both", "gsplat", "gsw"), default="both")
    ap.add_argument("--tag", default="gsplat_strategy")
    ap.add_argument("--sh-schedule", choices=("ramp", "full"), default="ramp",
                    help="both loops: SH degree 0 -> 3 every 250 steps (ramp), or degree 3 from the first step")
    ap.add_argument("--no-opacity-resets", dest="opacity_resets", action="store_false",
                    help="run DefaultStrategy as shipped (its opacity reset never fires); recorded as gsplat_as_shipped")
    args = ap.parse_args()
    import gsplat  # noqa: PLC0415  (fail early when it is missing)

    train_set = load_nerf_synthetic(args.data, "train", downscale=args.downscale, background=(1, 1, 1))
    test_set = load_nerf_synthetic(args.data, "test", downscale=args.downscale, background=(1, 1, 1))
    extent = scene_extent(list(train_set.cameras))[1]
    lo, hi = init_box(list(train_set.cameras), TrainConfig().init_box_scale)
    g0 = random_init(args.init_points, lo, hi, sh_degree=3, opacity=0.1, seed=args.seed)
    out = RESULTS / f"{args.tag}.json"
    summary: dict[str, Any] = {}
    summary.update({"iterations": args.iterations, "sh_schedule": args.sh_schedule, "seed": args.seed,
                    "init_points": args.init_points,
                    "scene_extent": extent,
                    "num_test_views": len(test_set), "torch": torch.__version__, "gsplat": gsplat.__version__,
                    "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
                               f"{torch.get_num_threads()} torch threads, load {os.getloadavg()}",
                    "command": " ".join(["python", "benchmarks/gsplat_strategy.py", *sys.argv[1:]])})
    RESULTS.mkdir(parents=True, exist_ok=True)
    for name in (("gsplat", "gsw") if args.which == "both" else (args.which,)):
        result = (run_gsplat(train_set, test_set, g0, extent, args) if name == "gsplat"
                  else run_gsw(train_set, test_set, g0, args))
        if name == "gsplat" and not args.opacity_resets:
            name = "gsplat_as_shipped"
        # runs of the other trainer written meanwhile (``--which`` runs in parallel processes) are kept
        old = json.loads(out.read_text()) if out.exists() else {}
        runs = summary["runs"] = {k: v for k, v in old.get("runs", {}).items()
                                  if [old.get(k) for k in ("iterations", "sh_schedule", "seed")]
                                  == [args.iterations, args.sh_schedule, args.seed]}
        runs[name] = {**result, "load_avg_end": os.getloadavg()}
        print(f"[{name}] test PSNR {runs[name]['test_psnr']:.2f} dB", flush=True)
        if "gsplat" in runs and "gsw" in runs:
            summary["psnr_diff_db"] = runs["gsplat"]["test_psnr"] - runs["gsw"]["test_psnr"]
            summary["within_0_5_db"] = bool(math.fabs(summary["psnr_diff_db"]) <= 0.5)
        with atomic_write(out, "w") as f:
            json.dump(summary, f, indent=1)
        write_markdown(summary, RESULTS / f"{args.tag}.md")


if __name__ == "__main__":
    main()
