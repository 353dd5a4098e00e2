"""What FGD alone costs in invisibility: PSNR of the FGD-densified model (prune + split, before any fine-tuning)
against the input model, on the held-out views of the built-in scene or a trained model (issue #23, BENCHMARKS.md §9j).

The split (:func:`gsw.mark.fgd.split_gaussians`) replaces each chosen Gaussian by two moment-matched children; on
a scene of nearly opaque Gaussians their composite is not the parent's footprint, so the render changes before
the fine-tune has begun, and the fine-tune must spend steps (and, at a PSNR target, invisibility budget) undoing
it.

Usage:
    python benchmarks/fgd_split_cost.py --size 256 --out benchmarks/results/fgd_split_cost_builtin256.json
    python benchmarks/fgd_split_cost.py --model build/train_lego/train_lego_model --data ../shared/data/lego \
        --downscale 4 --eval-views 13 --out benchmarks/results/fgd_split_cost_lego200.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256, help="built-in scene render size")
    ap.add_argument("--views", type=int, default=24, help="built-in scene: embedding views (FGD's views)")
    ap.add_argument("--model", type=Path, default=None, help="an INRIA model folder instead of the built-in scene")
    ap.add_argument("--data", type=Path, default=None, help="with --model: its dataset (train / test splits)")
    ap.add_argument("--downscale", type=float, default=1.0, help="with --model: image and camera size divisor")
    ap.add_argument("--eval-views", type=int, default=None, help="with --model: the first this many test views")
    ap.add_argument("--opacity-rule", default="coincident", help="the split children's opacity rule "
                    "(gsw.mark.fgd.SPLIT_OPACITY_RULES)")
    ap.add_argument("--out", type=Path, default=None, help="JSON file for the result")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import gsw
    from fingerprint_throughput import held_out_scores  # beside this script
    from gsw.eval.grid import default_grid_scene, load_grid_scene
    from gsw.mark.fgd import fgd_prune, fgd_split
    from gsw.render.rasterize import rasterize

    if args.model is None:
        scene = default_grid_scene(size=args.size, views=args.views)
    else:
        scene = load_grid_scene(args.model, args.data, downscale=args.downscale, white=True, eval_views=args.eval_views)
    g, bg = scene.gaussians, scene.background
    originals = [rasterize(g, cam, background=bg).image.clamp(0, 1) for cam in scene.eval_cameras]

    pruned, prune = fgd_prune(g, scene.cameras, None, background=bg)
    split, _ = fgd_split(pruned, scene.cameras, background=bg, opacity_rule=args.opacity_rule)
    _, after = held_out_scores(split, originals, scene.eval_cameras, bg)
    cam = scene.cameras[0]
    out = dict(scene="builtin" if args.model is None else str(args.model), size=[cam.width, cam.height],
               opacity_rule=args.opacity_rule, embedding_views=len(scene.cameras), gaussians=len(g),
               pruned=prune.num_removed, after_fgd=len(split), held_out_views=len(after),
               psnr_mean=sum(after) / len(after), psnr_min=min(after),
               opacity_quartiles=torch.quantile(g.opacities.float(), torch.tensor([0.25, 0.5, 0.75])).tolist(),
               machine=dict(torch=torch.__version__, python=platform.python_version(), gsw=gsw.__version__,
                            cpu=platform.processor() or platform.machine()))
    print(json.dumps(out))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
