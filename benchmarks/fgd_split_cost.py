"""What FGD alone costs in invisibility: PSNR of the FGD-densified model (prune + split, before any fine-tuning)
against the input model, on the held-out views of the built-in scene (issue #23, BENCHMARKS.md §9j).

The split (:func:`gsw.mark.fgd.split_gaussians`) replaces each chosen Gaussian by two moment-matched children; on
a scene of nearly opaque Gaussians their composite is not the parent's footprint, so the render changes before
the fine-tune has begun, and the fine-tune must spend steps (and, at a PSNR target, invisibility budget) undoing
it.

Usage:
    python benchmarks/fgd_split_cost.py --size 256 --out benchmarks/results/fgd_split_cost_builtin256.json
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
    ap.add_argument("--views", type=int, default=24, help="embedding views (FGD's views)")
    ap.add_argument("--out", type=Path, default=None, help="JSON file for the result")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    import gsw
    from gsw.eval.grid import default_grid_scene
    from gsw.mark.fgd import fgd_prune, fgd_split
    from gsw.metrics.image import psnr
    from gsw.render.rasterize import rasterize

    scene = default_grid_scene(size=args.size, views=args.views)
    g, bg = scene.gaussians, scene.background
    originals = [rasterize(g, cam, background=bg).image.clamp(0, 1) for cam in scene.eval_cameras]

    def held_out_psnr(model) -> list[float]:
        return [float(psnr(rasterize(model, cam, background=bg).image.clamp(0, 1), ref))
                for cam, ref in zip(scene.eval_cameras, originals)]

    pruned, prune = fgd_prune(g, scene.cameras, None, background=bg)
    split, _ = fgd_split(pruned, scene.cameras, background=bg)
    after = held_out_psnr(split)
    out = dict(scene="builtin", size=args.size, gaussians=len(g), pruned=prune.num_removed,
               after_fgd=len(split), held_out_views=len(after), psnr_mean=sum(after) / len(after),
               psnr_min=min(after), opacity_quartiles=torch.quantile(g.opacities.float(), torch.tensor(
                   [0.25, 0.5, 0.75])).tolist(),
               machine=dict(torch=torch.__version__, python=platform.python_version(), gsw=gsw.__version__,
                            cpu=platform.processor() or platform.machine()))
    print(json.dumps(out))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
