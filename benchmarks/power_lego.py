"""Power of the calibrated detector on lego (issue #22): detection at 1e-6 of held-out renders at 0.5x-3x.

Steps (one process, GPU recommended):

1. train 3DGS on NeRF-synthetic lego (every 8th view held out; INRIA recipe compressed to
   ``--iterations``, stopped at ``--train-seconds``), white background, ``--size`` pixels;
2. embed a ``--bits`` message with :class:`gsw.mark.embed.EmbedConfig`'s defaults (8 epochs, FGD, exp mask),
   (``--lpips`` picks another LPIPS network; the weights ship with gsw);
3. held-out views: the 13 held-out lego cameras and ``--orbit`` orbit cameras (elevations 20/35/50 deg,
   azimuths between the training views') -- none of them used for embedding; each rendered at
   0.5x, 1x, 1.5x, 2x and 3x the embedding size (intrinsics scaled);
4. :func:`gsw.verify` per view (single views) with the embedding size known (``embed_size``, read at that
   size) and unknown (the scale search, counted in the p-value), and sets of 10 views (every window of 10
   consecutive held-out views, Hommel combination); the detection rate at 1e-6 of each;
5. control: the unmarked model's renders at 1x against the same message.

Writes JSON to ``--out`` (default ``benchmarks/results/power_lego.json``) and, when ``$OUT`` is set, a copy there.

    PYTHONPATH=. python benchmarks/power_lego.py --data ../shared/data/lego --device cuda

Needs kornia (the 3DGS training's SSIM term). On the lent GPU machine, carry the lego folder in an ignored
folder (the whole transfer is limited to 64 MiB: e.g. the photos as WebP) and install the wheels of ``.whl/``
(kornia, kornia_rs) before building.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
SCALES = (0.5, 1.0, 1.5, 2.0, 3.0)
FPR = 1e-6
SET_SIZE = 10


def held_out_cameras(test_cams, n_orbit: int):
    """The held-out lego cameras plus ``n_orbit`` orbit cameras of the same intrinsics (white-box novel views)."""
    from gsw.camera import orbit_cameras

    ref = test_cams[0]
    radius = float(ref.center.double().norm())
    fov = math.degrees(ref.fov_x)
    per_ring = max(1, n_orbit // 3)
    cams = list(test_cams)
    for r, elev in enumerate((20.0, 35.0, 50.0)):
        cams += orbit_cameras((0.0, 0.0, 0.0), radius, per_ring, width=ref.width, height=ref.height,
                              elevation_deg=elev, fov_x_deg=fov, azimuth_offset_deg=7.0 + 5.0 * r)
    return cams


def render(g, cams, bg):
    from gsw.render.rasterize import rasterize

    with torch.no_grad():
        return [rasterize(g, c, background=bg).image.clamp(0, 1) for c in cams]


def rates(p_values: list[float]) -> dict:
    """Detection rate at :data:`FPR` of single views and of every cyclic window of :data:`SET_SIZE` views."""
    from gsw.stats import hommel_combined_p_value

    n = len(p_values)
    sets = [hommel_combined_p_value([p_values[(i + j) % n] for j in range(SET_SIZE)]) for i in range(n)]
    return {"single": sum(p <= FPR for p in p_values) / n, "single_detected": sum(p <= FPR for p in p_values),
            "views": n, "sets_of_10": sum(p <= FPR for p in sets) / n, "sets": n,
            "median_p": sorted(p_values)[n // 2], "max_p": max(p_values)}


def train_lego(args, dev):
    from gsw.data.loaders import load_nerf_synthetic
    from gsw.train import TrainConfig, train

    down = 800 / args.size
    train_set = load_nerf_synthetic(args.data, "train", downscale=down)
    test_set = load_nerf_synthetic(args.data, "test", downscale=down)
    cfg = TrainConfig.scaled(args.iterations, max_train_time_s=args.train_seconds, device=str(dev), seed=0)
    res = train(train_set, config=cfg, progress=False, test_set=test_set, background=(1.0, 1.0, 1.0))
    info = {"iterations": res.iterations, "train_time_s": res.train_time_s, "gaussians": len(res.gaussians),
            "test_psnr": (res.test_metrics or {}).get("psnr")}
    print("trained", info, flush=True)
    return res.gaussians, train_set, test_set, info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "lego")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "power_lego.json")
    ap.add_argument("--size", type=int, default=800, help="embedding render size (lego: 800 = native)")
    ap.add_argument("--iterations", type=int, default=12000)
    ap.add_argument("--train-seconds", type=float, default=100.0)
    ap.add_argument("--bits", type=int, default=32)
    ap.add_argument("--epochs", type=int, default=None, help="default: EmbedConfig's")
    ap.add_argument("--lpips", default="vgg", choices=["alex", "vgg", "none"])
    ap.add_argument("--orbit", type=int, default=72, help="extra held-out orbit views")
    ap.add_argument("--scales", type=float, nargs="+", default=list(SCALES))
    ap.add_argument("--device", default="auto")
    args = ap.parse_args()

    from gsw.device import resolve_device
    from gsw.mark import EmbedConfig, embed, verify
    from gsw.mark.loss import lpips_weights
    from gsw.mark.message import random_message

    t0 = time.perf_counter()
    dev = resolve_device(args.device)
    g, train_set, test_set, train_info = train_lego(args, dev)
    bg = (1.0, 1.0, 1.0)
    lp = None if args.lpips == "none" else args.lpips
    cfg = EmbedConfig(background=bg, lpips_net=lp, weights=lpips_weights(lp))
    if args.epochs is not None:
        cfg.epochs = args.epochs
    message = random_message(args.bits, seed=2222)  # fixed: the run is reproducible
    t1 = time.perf_counter()
    res = embed(g, train_set.cameras, message=message, num_bits=args.bits,
                images=[im.to(dev) for im in train_set.images], config=cfg, progress=False)
    embed_s = time.perf_counter() - t1
    print(f"embedded in {embed_s:.1f} s, train-view bit accuracy {sum(res.bit_accuracy) / len(res.bit_accuracy):.4f}",
          flush=True)
    cams = held_out_cameras(test_set.cameras, args.orbit)
    size = (cams[0].height, cams[0].width)
    out: dict = {
        "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor(),
        "torch": torch.__version__, "python": platform.python_version(), "settings": vars(args) | {"data": str(args.data),
                                                                                                 "out": str(args.out)},
        "train": train_info, "embed": {"seconds": embed_s, "config": {"epochs": cfg.epochs, "lpips": lp, "fgd": cfg.fgd,
                                                                        "mask": cfg.mask},
                                       "gaussians": len(res.gaussians),
                                       "train_bit_accuracy": sum(res.bit_accuracy) / len(res.bit_accuracy),
                                       "train_psnr": sum(res.psnr) / len(res.psnr)},
        "held_out_views": len(cams), "embed_size": list(size), "fpr": FPR, "scales": {},
    }
    for s in args.scales:
        imgs = render(res.gaussians, [c.scaled(s) for c in cams], bg)
        known = verify(imgs, message, num_bits=args.bits, embed_size=size)
        search = verify(imgs, message, num_bits=args.bits)
        out["scales"][f"{s:g}x"] = {"render_size": list(imgs[0].shape[-2:]),
                                    "bit_accuracy_known_size": sum(known.bit_accuracy) / len(imgs),
                                    "bit_accuracy_search": sum(search.bit_accuracy) / len(imgs),
                                    "known_size": rates(known.p_values), "search": rates(search.p_values)}
        print(f"{s:g}x", json.dumps(out["scales"][f"{s:g}x"]), flush=True)
        del imgs
    control = verify(render(g, cams, bg), message, num_bits=args.bits, embed_size=size)
    out["unmarked_control_1x"] = {"known_size": rates(control.p_values),
                                  "bit_accuracy": sum(control.bit_accuracy) / len(cams)}
    out["seconds"] = time.perf_counter() - t0
    text = json.dumps(out, indent=1) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    if os.environ.get("OUT"):
        Path(os.environ["OUT"], args.out.name).write_text(text)
    print(json.dumps({k: v for k, v in out.items() if k != "settings"}, indent=1))


if __name__ == "__main__":
    main()
