"""The evaluation grid (`gsw.grid`) on the lego model trained by `benchmarks/train_lego.py`.

Every (method, bits, seed) cell embeds into the INRIA model folder with the NeRF-synthetic lego train views
(../shared/data/lego at the model's resolution, white background) and is evaluated on the held-out views (every
8th): bit accuracy and TPR / empirical FPR at 1e-6, clean and under the image and model attacks, robustness
curves, PSNR/SSIM/LPIPS against the original renders, time, FPS and storage. Defaults: the paper's grid (every
method of `gsw.eval.grid.METHODS` at 32/48/64 bits, seeds 0-2, 8 epochs). The cells stay in `build/eval_grid/<tag>/`
(git-ignored; rerun the same command to resume) and the summary goes to `benchmarks/results/<tag>.{json,md}`.

Usage:
    python benchmarks/eval_grid.py [--methods 3d-gsw no-fgd] [--bits 32] [--seeds 0] [--epochs 8] [--device cuda]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
LEGO_SIZE = 800  # NeRF-synthetic image size


def parse_args() -> argparse.Namespace:
    from gsw.eval.grid import GridSpec

    default = GridSpec()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=ROOT / "build" / "train_lego" / "train_lego_model")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "lego")
    ap.add_argument("--methods", nargs="+", default=list(default.methods))
    ap.add_argument("--bits", nargs="+", type=int, default=list(default.bits))
    ap.add_argument("--seeds", nargs="+", type=int, default=list(default.seeds))
    ap.add_argument("--epochs", type=int, default=default.epochs)
    ap.add_argument("--sweeps", nargs="*", default=list(default.sweeps))
    ap.add_argument("--message-weight", type=float, default=None,
                    help="weight of the message BCE term for every method (default: LossWeights.message)")
    ap.add_argument("--model-attacks", nargs="*", default=list(default.model_attacks),
                    help="keys of gsw.attacks.presets.MODEL_ATTACKS or VIEW_MODEL_ATTACKS (finetune)")
    ap.add_argument("--lpips", default="alex", choices=["vgg", "alex", "none"], help="LPIPS term of the embedding loss")
    ap.add_argument("--metric-lpips", default="vgg", choices=["vgg", "alex", "none"], help="LPIPS of the report")
    ap.add_argument("--train-views", type=int, default=None, help="evenly spaced embedding views (default: all 87)")
    ap.add_argument("--eval-views", type=int, default=None, help="first N held-out views (default: all 13)")
    ap.add_argument("--device", default="auto", help="cpu, cuda[:N] or auto")
    ap.add_argument("--tag", default=None, help="results name (default eval_grid, eval_grid_cuda on a GPU)")
    ap.add_argument("--force", action="store_true", help="replace the settings of an existing grid folder")
    ap.add_argument("--no-progress", action="store_true")
    return ap.parse_args()


def main() -> int:
    import gsw
    from gsw.eval.grid import GridSpec, load_grid_scene, lpips_loss_overrides, run_grid
    from gsw.train import resolve_device

    args = parse_args()
    dev = resolve_device(args.device)
    tag = args.tag or ("eval_grid_cuda" if dev.type == "cuda" else "eval_grid")
    size = json.loads((args.model / "cameras.json").read_text())[0]["width"]
    scene = load_grid_scene(args.model, args.data, downscale=LEGO_SIZE / size, white=True,
                            train_views=args.train_views, eval_views=args.eval_views)
    scene = scene.to(dev)
    embed_overrides = lpips_loss_overrides(None if args.lpips == "none" else args.lpips)
    if args.message_weight is not None:
        embed_overrides["weights"] = {**embed_overrides.get("weights", {}), "message": args.message_weight}
    spec = GridSpec(methods=tuple(args.methods), bits=tuple(args.bits), seeds=tuple(args.seeds), epochs=args.epochs,
                    sweeps=tuple(args.sweeps), model_attacks=tuple(args.model_attacks),
                    embed=embed_overrides,
                    lpips_net=None if args.metric_lpips == "none" else args.metric_lpips)
    start = time.perf_counter()
    summary = run_grid(spec, scene, ROOT / "build" / "eval_grid" / tag, force=args.force,
                       progress=not args.no_progress)
    machine = dict(cpu=platform.processor(), threads=torch.get_num_threads(), device=str(dev),
                   gpu=torch.cuda.get_device_name(dev) if dev.type == "cuda" else None, torch=torch.__version__,
                   python=platform.python_version(), gsw=gsw.__version__, date=time.strftime("%Y-%m-%d %H:%M:%S"))
    command = " ".join(["python", "benchmarks/eval_grid.py", *sys.argv[1:]])
    results = {**summary.to_dict(), "model": str(args.model), "resolution": size, "command": command,
               "wall_time_s": time.perf_counter() - start, "machine": machine}
    out = ROOT / "benchmarks" / "results"
    (out / f"{tag}.json").write_text(json.dumps(results, indent=1) + "\n")
    header = (f"Lego {size}x{size} ({len(scene.gaussians):,} Gaussians from `benchmarks/train_lego.py`), "
              f"{len(scene.cameras)} embedding views, {len(scene.eval_cameras)} held-out evaluation views; "
              f"embedding LPIPS {args.lpips}, metric LPIPS {args.metric_lpips}; {machine['gpu'] or 'CPU'}, torch "
              f"{machine['torch']}, {machine['threads']} threads, {machine['date']}; cells computed this run "
              f"{summary.computed}, reused {summary.reused}. Reproduce: `{command}`.")
    markdown = summary.to_markdown().replace("\n", f"\n\n{header}\n", 1)
    (out / f"{tag}.md").write_text(markdown)
    print(markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
