"""3D-GSW on a lego model trained by `benchmarks/train_lego.py`: capacity, invisibility, FGD.

Loads the INRIA model folder, embeds 32/48/64-bit messages with the training views (every view
that is not a multiple of 8), and evaluates on the held-out views (every 8th): bit accuracy,
per-view p-values, PSNR/SSIM/LPIPS against renders of the original model (the paper's protocol)
and against the ground-truth photos, the unmarked model's decode accuracy, FGD statistics and
render speed / size before and after. Writes `benchmarks/results/embed_lego.{json,md}`.

Usage:
    python benchmarks/embed_lego.py --model build/train_lego/train_lego_model [--bits 32 48 64]
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


def _mean(xs):
    xs = list(xs)
    return sum(xs) / len(xs)


def main() -> int:
    import gsw
    from gsw.data import load_inria_model, load_nerf_synthetic
    from gsw.mark import EmbedConfig, embed, verify
    from gsw.mark.fgd import PRUNE_THRESHOLD, fgd_prune
    from gsw.mark.loss import LossWeights, lpips_weights
    from gsw.mark.message import random_message
    from gsw.metrics.image import psnr, ssim
    from gsw.train import resolve_device
    from gsw.decoder.pretrain.evaluation import unbiasedness
    from gsw.metrics.lpips import lpips
    from gsw.decoder.zoo import load_decoder

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=str(ROOT / "build" / "train_lego" / "train_lego_model"))
    parser.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "lego"))
    parser.add_argument("--bits", type=int, nargs="+", default=[32, 48, 64])
    parser.add_argument("--epochs", type=int, default=8)
    parser.add_argument("--lpips", default="alex", choices=["alex", "vgg", "none"])
    parser.add_argument("--metric-lpips", default="vgg", choices=["alex", "vgg"], help="LPIPS network of the report")
    parser.add_argument("--mask", default="exp", choices=["exp", "stega", "none"])
    parser.add_argument("--attacks", type=float, default=0.0)
    parser.add_argument("--message-weight", type=float, default=LossWeights.message, help="weight of the BCE term")
    parser.add_argument("--lr-f-dc", type=float, default=EmbedConfig.lr_f_dc)
    parser.add_argument("--lr-f-rest", type=float, default=EmbedConfig.lr_f_rest)
    parser.add_argument("--tag", default=None, help="results name (default embed_lego, embed_lego_cuda on a GPU)")
    parser.add_argument("--device", default="auto", help="cpu, cuda[:N] or auto")
    parser.add_argument("--size", type=int, default=None,
                        help="render size in pixels (default: the model's training resolution)")
    parser.add_argument("--unmarked-messages", type=int, default=1000,
                        help="random messages the unmarked model's code is compared with")
    parser.add_argument("--prune-sweep", type=float, nargs="*", default=[],
                        help="also report FGD phase 1 at these multiples of the default threshold")
    args = parser.parse_args()

    dev = resolve_device(args.device)
    args.tag = args.tag or ("embed_lego_cuda" if dev.type == "cuda" else "embed_lego")
    model = load_inria_model(args.model)
    g, size = model.gaussians.to(dev), args.size or model.cameras[0].width
    downscale = 800 / size
    train = load_nerf_synthetic(args.data, "train", downscale=downscale)
    test = load_nerf_synthetic(args.data, "test", downscale=downscale)
    train_images = [im.to(dev) for im in train.images]
    test_images = [im.to(dev) for im in test.images]
    bg = (1.0, 1.0, 1.0)
    lp = None if args.lpips == "none" else args.lpips

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    def quality(a_model, b_model, cams, gt=None):
        rows = []
        with torch.no_grad():
            for i, cam in enumerate(cams):
                a = gsw.rasterize(a_model, cam, background=bg).image.clamp(0, 1)
                b = gsw.rasterize(b_model, cam, background=bg).image.clamp(0, 1)
                r = dict(psnr=float(psnr(b, a)), ssim=float(ssim(b, a)),
                         lpips=float(lpips(b[None], a[None], net=args.metric_lpips)))
                if gt is not None:
                    r["psnr_gt"] = float(psnr(b, gt[i]))
                    r["psnr_gt_original"] = float(psnr(a, gt[i]))
                rows.append(r)
        return rows

    def fps(m, cams, repeats=3):
        with torch.no_grad():
            gsw.rasterize(m, cams[0], background=bg)
            sync()
            start = time.perf_counter()
            for _ in range(repeats):
                for cam in cams:
                    gsw.rasterize(m, cam, background=bg, validate=False)
            sync()
            return repeats * len(cams) / (time.perf_counter() - start)

    results = dict(model=str(args.model), gaussians=len(g), size=size, train_views=len(train.cameras),
                   test_views=len(test.cameras), settings=vars(args))
    # FGD phase 1 alone: how much it removes and what it costs in quality.
    pruned, prune = fgd_prune(g, train.cameras, train_images, background=bg)
    q_pruned = quality(g, pruned, test.cameras, gt=test_images)
    results["fgd_prune"] = dict(removed=prune.num_removed, fraction=prune.fraction_removed,
                                psnr_vs_original=_mean(r["psnr"] for r in q_pruned),
                                psnr_gt=_mean(r["psnr_gt"] for r in q_pruned),
                                psnr_gt_original=_mean(r["psnr_gt_original"] for r in q_pruned))
    results["speed"] = dict(fps_original=fps(g, test.cameras), fps_pruned=fps(pruned, test.cameras),
                            ply_mb_original=len(g) * 62 * 4 / 2**20,
                            ply_mb_pruned=len(pruned) * 62 * 4 / 2**20)
    results["fgd_sweep"] = []
    for mult in args.prune_sweep:  # the same per-Gaussian contributions, other thresholds
        keep = prune.max_contribution > PRUNE_THRESHOLD * mult
        q_kept = quality(g, g[keep], test.cameras, gt=test_images)
        results["fgd_sweep"].append(dict(threshold=PRUNE_THRESHOLD * mult, removed=int((~keep).sum()),
                                         fraction=float((~keep).float().mean()),
                                         psnr_vs_original=_mean(r["psnr"] for r in q_kept),
                                         psnr_gt=_mean(r["psnr_gt"] for r in q_kept)))
    print(json.dumps(results, indent=1), flush=True)

    def unmarked_over_messages(k):
        # The unmarked model decodes to one fixed code per view; its agreement with a single message is one
        # binomial draw, so also compare it with many random messages (the decoder issue's protocol).
        with torch.no_grad():
            renders = [gsw.rasterize(g, cam, background=bg).image.clamp(0, 1) for cam in test.cameras]
        u = unbiasedness(load_decoder(k).to(dev).eval(), renders, k, args.unmarked_messages, seed=k, device=dev)
        return dict(mean=u["mean_bit_acc"], pairs_p_le_1e6=u["false_positives"],
                    pairs=u["num_images"] * u["num_messages"], views_code_p1=u["per_bit_p1"])

    results["bits"] = {}
    for k in args.bits:
        cfg = EmbedConfig(epochs=args.epochs, background=bg, lpips_net=lp, mask=args.mask,
                          attacks=args.attacks, lr_f_dc=args.lr_f_dc, lr_f_rest=args.lr_f_rest,
                          weights=lpips_weights(lp, LossWeights(message=args.message_weight)))
        res = embed(g, train.cameras, message=random_message(k, seed=cfg.seed), num_bits=k, images=train_images,
                    config=cfg, progress=True)
        v = verify((res.gaussians, test.cameras), res.message, background=bg)
        v0 = verify((g, test.cameras), res.message, background=bg)
        q = quality(g, res.gaussians, test.cameras, gt=test_images)
        results["bits"][k] = dict(
            message=res.message_hex, bit_accuracy=_mean(v.bit_accuracy),
            bit_accuracy_min=min(v.bit_accuracy),
            views_p_le_1e6=sum(p <= 1e-6 for p in v.p_values) / len(v.p_values),
            combined_p=v.p_value, unmarked_bit_accuracy=_mean(v0.bit_accuracy),
            unmarked_random_messages=unmarked_over_messages(k),
            psnr=_mean(r["psnr"] for r in q), ssim=_mean(r["ssim"] for r in q),
            lpips=_mean(r["lpips"] for r in q), psnr_gt=_mean(r["psnr_gt"] for r in q),
            psnr_gt_original=_mean(r["psnr_gt_original"] for r in q),
            gaussians_after=len(res.gaussians), pruned=res.prune.num_removed, split=res.split.num_split,
            fps_after=fps(res.gaussians, test.cameras), timings=res.timings,
            train_bit_accuracy=_mean(res.bit_accuracy))
        print(json.dumps(results["bits"][k], indent=1), flush=True)

    results["machine"] = dict(cpu=platform.processor(), threads=torch.get_num_threads(), device=str(dev),
                              gpu=torch.cuda.get_device_name(dev) if dev.type == "cuda" else None,
                              torch=torch.__version__, python=platform.python_version(),
                              gsw=gsw.__version__, build=gsw.build_info(),
                              date=time.strftime("%Y-%m-%d %H:%M:%S"))
    out = ROOT / "benchmarks" / "results"
    (out / f"{args.tag}.json").write_text(json.dumps(results, indent=2) + "\n")
    where = results["machine"]["gpu"] or "CPU"
    lines = [f"# 3D-GSW on lego ({size}x{size}, {where})", "",
             f"Model: {len(g):,} Gaussians from `benchmarks/train_lego.py`; {len(train.cameras)} training "
             f"views for embedding, {len(test.cameras)} held-out views (every 8th) for evaluation. "
             f"Settings: {args.epochs} epochs, LPIPS term {args.lpips}, mask {args.mask}, train-time "
             f"attacks {args.attacks}, learning rates f_dc {args.lr_f_dc:g} / f_rest {args.lr_f_rest:g}, message "
             f"weight {args.message_weight:g}. Metrics vs renders of the original model (paper protocol); "
             f"LPIPS network: {args.metric_lpips}. torch {torch.__version__}, {torch.get_num_threads()} threads, "
             f"{results['machine']['date']}.", "",
             "| bits | bit acc (held-out) | min view | views p<=1e-6 | unmarked acc (this msg.) | "
             f"unmarked acc ({args.unmarked_messages:,} msgs.) | unmarked pairs p<=1e-6 | PSNR | SSIM | "
             "LPIPS | PSNR vs GT (orig.) | Gaussians after | time |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for k, r in results["bits"].items():
        lines.append(f"| {k} | {100 * r['bit_accuracy']:.2f} % | {100 * r['bit_accuracy_min']:.1f} % | "
                     f"{100 * r['views_p_le_1e6']:.0f} % | {100 * r['unmarked_bit_accuracy']:.1f} % | "
                     f"{100 * r['unmarked_random_messages']['mean']:.1f} % | "
                     f"{r['unmarked_random_messages']['pairs_p_le_1e6']} of {r['unmarked_random_messages']['pairs']:,} | "
                     f"{r['psnr']:.2f} | {r['ssim']:.4f} | {r['lpips']:.4f} | {r['psnr_gt']:.2f} "
                     f"({r['psnr_gt_original']:.2f}) | {r['gaussians_after']:,} | "
                     f"{r['timings']['total']:.0f} s |")
    fp, sp = results["fgd_prune"], results["speed"]
    lines += ["", f"FGD phase 1 on the trained model: removed {fp['removed']:,} of {len(g):,} "
              f"({100 * fp['fraction']:.1f} %); pruned model vs original renders {fp['psnr_vs_original']:.2f} dB, "
              f"vs the photos {fp['psnr_gt']:.2f} dB (original {fp['psnr_gt_original']:.2f} dB); "
              f"{where} render speed {sp['fps_original']:.1f} -> {sp['fps_pruned']:.1f} FPS; PLY size "
              f"{sp['ply_mb_original']:.1f} -> {sp['ply_mb_pruned']:.1f} MB."]
    if results["fgd_sweep"]:
        lines += ["", "FGD phase 1 threshold sweep (held-out views, pruned model vs original renders):", "",
                  "| threshold | removed | fraction | PSNR vs original | PSNR vs photos |", "|---|---|---|---|---|"]
        lines += [f"| {r['threshold']:.0e} | {r['removed']:,} | {100 * r['fraction']:.1f} % | "
                  f"{r['psnr_vs_original']:.2f} dB | {r['psnr_gt']:.2f} dB |" for r in results["fgd_sweep"]]
    (out / f"{args.tag}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
