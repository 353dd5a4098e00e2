"""Writes the blend-kernel inputs of one benchmark scene (100k Gaussians at 800x800, SH 3) as raw files for harness.cpp.

Usage: python benchmarks/kernel_icount/dump_inputs.py frustum|heavy OUTDIR
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from bench_cpu import family_scene  # noqa: E402
from gsw._ext import _C  # noqa: E402
from gsw.render import _ops  # noqa: E402


def main() -> int:
    family, out = sys.argv[1], sys.argv[2]
    os.makedirs(out, exist_ok=True)
    size, degree = 800, 3
    g, cam = family_scene(family, 100_000, size, size, degree)
    camera = (cam.viewmat, float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy), size, size)
    radii, means2d, conics, depths, colors, opacities, _ = _ops.project(
        g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, degree, *camera, False)
    b = _ops.bins(means2d, conics, opacities, radii, depths, size, size)
    _, _, _, final_T, n_contrib = _C.rasterize_forward(means2d, conics, colors, opacities, depths, torch.zeros(3), bins=b,
                                                       width=size, height=size)
    tensors = dict(means2d=means2d, conics=conics, colors=colors, opacities=opacities, depths=depths,
                   tile_offsets=b.tile_offsets, gauss_ids=b.gauss_ids, entry_offsets=b.entry_offsets,
                   entry_slots=b.entry_slots, final_T=final_T, n_contrib=n_contrib)
    for name, t in tensors.items():
        t.contiguous().numpy().tofile(f"{out}/{name}.bin")
    with open(f"{out}/meta.txt", "w") as f:
        f.write(f"{means2d.shape[0]} {size} {size} {b.tiles_x} {b.tiles_y} {int(b.num_intersections)}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
