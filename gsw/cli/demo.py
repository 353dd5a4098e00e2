"""`gsw demo`: watermark the built-in scene, read it back on held-out views, print a table (or JSON), write PNGs.

Unlike `gsw embed`, the demo is reproducible: without ``--message`` / ``--key`` its message is drawn from
``--seed`` (a public message: seed 0 at 32 bits gives ``6fe4167a``), so `make demo` prints the same table
on every run.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from gsw.cli.common import add_message_options, message_from_args, positive_int, print_json
from gsw.stats import DETECTION_FPR


def register(subparsers: argparse._SubParsersAction) -> None:
    """Adds ``demo``."""
    demo = subparsers.add_parser("demo", help="watermark the built-in scene and read it back (no downloads)")
    demo.add_argument("--output", default="gsw-demo", help="output folder (default: gsw-demo)")
    demo.add_argument("--size", type=positive_int, default=256,
                      help="render size (pixels; the decoder reads the 4x smaller LL2 subband)")
    demo.add_argument("--views", type=positive_int, default=24, help="training views")
    demo.add_argument("--epochs", type=positive_int, default=8)
    add_message_options(demo, claim=False, default_help="drawn from --seed: a public, reproducible demo message")
    demo.add_argument("--lpips", choices=["vgg", "alex", "none"], default="alex")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--no-progress", action="store_true")
    demo.add_argument("--json", action="store_true", help="print the results as JSON instead of the table")
    demo.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    """Built-in scene -> watermark -> detection on held-out views (:func:`gsw.eval.report.evaluate_watermark`)."""
    import torch

    import gsw
    from gsw.eval.report import evaluate_watermark
    from gsw.mark.embed import EmbedConfig, embed
    from gsw.mark.loss import lpips_weights
    from gsw.scenes import default_cameras, default_scene

    start = time.perf_counter()
    message, num_bits = message_from_args(args, required=False)
    if message is None:  # the demo is reproducible: its default message is public (seed 0, 32 bits: 6fe4167a)
        from gsw.mark.message import random_message

        message = random_message(num_bits, seed=args.seed)
    out_dir = Path(args.output)
    out_dir.mkdir(parents=True, exist_ok=True)
    scene = default_scene(width=args.size, height=args.size, n_cameras=args.views)
    bg = tuple(float(v) for v in torch.as_tensor(scene.background).flatten())
    g, cams = scene.gaussians, scene.cameras
    if not args.json:
        print(f"gsw {gsw.__version__} demo: built-in scene, {len(g):,} Gaussians (SH {g.sh_degree}), "
              f"{len(cams)} views at {args.size}x{args.size}, {num_bits}-bit message, "
              f"{torch.get_num_threads()} threads", flush=True)
    lpips_net = None if args.lpips == "none" else args.lpips
    cfg = EmbedConfig(epochs=args.epochs, background=bg, seed=args.seed, lpips_net=lpips_net,
                      weights=lpips_weights(lpips_net))
    res = embed(g, cams, message=message, num_bits=num_bits, config=cfg, progress=not args.no_progress)
    held_out = default_cameras(len(cams), args.size, args.size, azimuth_offset_deg=180.0 / len(cams))
    report = evaluate_watermark(res.gaussians, g, held_out, res.message, background=bg, image_attacks={},
                                model_attacks={}, lpips_net=lpips_net)
    images = _write_images(out_dir, g, res.gaussians, held_out[0], bg)
    results = _results(res, report, len(g), images, time.perf_counter() - start)
    if args.json:
        print_json(results)
    else:
        _print_table(results)
    return 0


def _write_images(out_dir: Path, original, marked, cam, bg: tuple[float, float, float]) -> list[str]:
    """original.png, watermarked.png and difference_x2.png of one held-out view."""
    import torch

    from gsw.data.images import write_image
    from gsw.render.rasterize import rasterize

    with torch.no_grad():
        a = rasterize(original, cam, background=bg).image.clamp(0, 1)
        b = rasterize(marked, cam, background=bg).image.clamp(0, 1)
    paths = [out_dir / "original.png", out_dir / "watermarked.png", out_dir / "difference_x2.png"]
    for path, img in zip(paths, (a, b, ((b - a).abs() * 2).clamp(0, 1))):
        write_image(path, img)
    return [str(p) for p in paths]


def _results(res, report, gaussians_in: int, images: list[str], seconds: float) -> dict[str, Any]:
    """The demo's numbers (JSON-able)."""
    from gsw.stats import fisher_combined_p_value

    p_values = report.clean.p_values
    return {
        "message": res.message_hex, "num_bits": int(res.message.numel()),
        "bit_accuracy": report.clean.bit_accuracy, "bit_accuracy_before": report.unmarked.bit_accuracy,
        "views": len(p_values), "detected_views": sum(p <= DETECTION_FPR for p in p_values),
        "fpr": DETECTION_FPR, "p_value": fisher_combined_p_value(p_values),
        "psnr": report.psnr, "ssim": report.ssim, "lpips": report.lpips,
        "gaussians_in": gaussians_in, "gaussians_out": len(res.gaussians),
        "pruned": res.prune.num_removed if res.prune else None, "split": res.split.num_split if res.split else None,
        "seconds": {"fgd": res.timings["fgd"], "finetune": res.timings["finetune"], "total": seconds},
        "images": images,
    }


def _print_table(r: dict[str, Any]) -> None:
    t = r["seconds"]
    rows = [
        ("message", r["message"]),
        ("bit accuracy, held-out views", f"{100 * r['bit_accuracy']:.2f} %"),
        ("bit accuracy, same views before embedding", f"{100 * r['bit_accuracy_before']:.2f} %"),
        (f"views with p <= {r['fpr']:g}", f"{r['detected_views']} / {r['views']}"),
        ("combined p-value", f"{r['p_value']:.2e}"),
        ("PSNR vs original render", f"{r['psnr']:.2f} dB"),
        ("SSIM vs original render", f"{r['ssim']:.4f}"),
        ("LPIPS vs original render", "off" if r["lpips"] is None else f"{r['lpips']:.4f}"),
        ("Gaussians: input / after FGD",
         f"{r['gaussians_in']:,} / {r['gaussians_out']:,} (pruned {r['pruned']:,}, split {r['split']:,})"
         if r["pruned"] is not None else f"{r['gaussians_in']:,} (FGD off)"),
        ("time: FGD / fine-tune / total", f"{t['fgd']:.1f} s / {t['finetune']:.1f} s / {t['total']:.1f} s"),
        ("images", ", ".join(r["images"])),
    ]
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k:<{width}}  {v}")
