"""Model formats on the shared PLY fixture: file size, largest parameter error and render PSNR after a round trip.

Renders 4 orbit views (:func:`gsw.io.convert.orbit_views`, 256x256, black background) of the original and of
the model written and read back in each format, and prints a markdown table.

Usage:
    python benchmarks/formats_fixture.py [--model ../shared/data/ply/sh3_fixture/point_cloud.ply]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch

import gsw
from gsw.io import load_gaussians
from gsw.io.convert import FORMAT_SUFFIXES, orbit_views
from gsw.io.compressed_ply import morton_order
from gsw.io.formats import WRITABLE_FORMATS, load_model, save_model
from gsw.metrics.image import psnr

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ply" / "sh3_fixture" / "point_cloud.ply"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=DEFAULT)
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--size", type=int, default=256)
    args = parser.parse_args()
    g = load_gaussians(args.model)
    cams = orbit_views(g, args.views, args.size)
    with torch.no_grad():
        ref = [gsw.rasterize(g, c).image.clamp(0, 1) for c in cams]
    print(f"{args.model.name}: {len(g):,} Gaussians, SH degree {g.sh_degree}, {args.views} orbit views "
          f"{args.size}x{args.size}\n")
    print("| format | bytes | max abs position error | render PSNR (dB), mean / worst view |")
    print("|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in WRITABLE_FORMATS:
            path = Path(tmp) / f"model{FORMAT_SUFFIXES[fmt]}"
            save_model(g, path, fmt)
            h = load_model(path, fmt)
            same = g[morton_order(g.means)] if fmt == "compressed-ply" else g
            err = float((h.means.double() - same.means.double()).abs().max())
            with torch.no_grad():
                values = [float(psnr(gsw.rasterize(h, c).image.clamp(0, 1)[None], r[None]))
                          for c, r in zip(cams, ref)]
            print(f"| {fmt} | {path.stat().st_size:,} | {err:.2e} | "
                  f"{sum(values) / len(values):.2f} / {min(values):.2f} |")


if __name__ == "__main__":
    main()
