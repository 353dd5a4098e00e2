"""Issue 23: a watermark for 3DGS in the wild -- any viewpoint, any render size, export formats, noise.

Embeds messages with named methods of :data:`gsw.eval.grid.METHODS` (``paper``: the paper-faithful recipe,
``wild``: sampled viewpoints and render sizes + train-time attacks and export distortions, or any other) into
a scene and measures, on held-out views (never embedded from):

* invisibility: PSNR / SSIM / LPIPS (AlexNet) against the original model's renders;
* bit accuracy clean, under the paper's image attacks, the model attacks (parameter noise, remove, clone)
  and the exports (SH degree 0, ``.splat``, ``.spz``, 8-bit, compressed PLY; real codecs);
* render size 0.5x / 1.5x / 2x / 3x: ``raw`` decodes the render as it is, ``read`` is :func:`gsw.verify`
  with the embedding size known (the image resized to it first, as ``gsw verify --model`` does);
* 24 novel viewpoints (8 azimuths between the training cameras x elevations -15, 15 and 60 degrees around the
  content centre at the cameras' median distance): bit accuracy and PSNR;
* embedding time (GPU synchronised).

``--bare``: the scene's model with its SH stripped to degree 0, embedded with no cameras at all (views sampled
around its content, 512 px), read on 24 random viewpoints around it at 512 and 256 px.

Scenes: ``--scene lego`` (an INRIA model folder from ``benchmarks/train_lego.py`` and the NeRF-synthetic data,
or a ``.spz`` with its camera files written by ``--prepare``; white background) or ``--scene builtin`` (the
built-in scene at ``--size``). No photos are used (FGD phase 1 weighs the original renders). Writes
``<out>/robust_wild_<tag>.json`` after every cell (so a stopped run keeps what it measured) and a markdown table.

``readout`` (a row key of ``--variant``, #22): ``"klein"`` embeds and reads every bit through
:class:`gsw.decoder.KleinReadout`, ``(D(ll) - D(h ll) - D(v ll) + D(r ll)) / 2`` on the decoder's LL2 input (h, v:
flips, r: the half turn), which cancels the decoder's per-bit lean; its ``clean_detected`` and size ``read`` p-values
come from gsw's tests for a custom decoder (the exact test; the fair coin for chosen messages).

Messages are reproducible (``--message-seed`` + the cell's seed), the same for every method. Subsets for quick
comparisons: ``--image-attacks`` / ``--model-attacks`` / ``--sizes`` (an empty list skips them), ``--eval-views``;
``--embed '{"field": value}'`` adds EmbedConfig overrides to every method.

Usage:
    python benchmarks/robust_wild.py --scene builtin --size 256 --methods paper wild --device cuda
    python benchmarks/robust_wild.py --scene lego --model build/train_lego/train_lego_model --methods paper wild
    python benchmarks/robust_wild.py --scene lego --data LEGO_WEBP --train-seconds 75 --methods paper freeze-rest
    python benchmarks/robust_wild.py --size 128 --device cpu --methods paper freeze-rest --image-attacks \
        --model-attacks reduce_sh export_splat --sizes
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
PAPER_IMAGE = ("noise", "rotation", "scaling", "blur", "crop", "jpeg", "combined")
MODEL = ("parameter_noise_attributes", "remove", "clone", "reduce_sh", "export_splat", "export_spz", "quantize",
         "export_compressed_ply", "parameter_noise")
SIZES = (0.5, 1.5, 2.0, 3.0)


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=["lego", "builtin"], default="builtin")
    ap.add_argument("--model", type=Path, default=ROOT / "build" / "train_lego" / "train_lego_model")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "lego")
    ap.add_argument("--cameras", type=Path, help="with a .spz --model: its embedding views (INRIA cameras.json)")
    ap.add_argument("--eval-cameras", type=Path, help="with a .spz --model: its held-out views")
    ap.add_argument("--prepare", type=Path, default=None,
                    help="lego: write the model through .spz (lego.spz) and its views (train/eval_cameras.json) "
                         "into this folder, and measure on that .spz-decoded model (so later runs can reuse it)")
    ap.add_argument("--train-seconds", type=float, default=None,
                    help="lego: train a model from --data for this long (benchmarks/power_lego.py's recipe; PNG or "
                         "WebP photos, WebP converted under --work) instead of loading --model")
    ap.add_argument("--work", type=Path, default=ROOT / "build" / "robust_wild_png",
                    help="where WebP photos are converted to PNG (with --train-seconds)")
    ap.add_argument("--size", type=int, default=256, help="built-in scene render size")
    ap.add_argument("--downscale", type=float, default=1.0,
                    help="lego from --model / --data: image and camera size divisor (4: the 200x200 CPU model)")
    ap.add_argument("--methods", nargs="*", default=["paper", "wild"])
    ap.add_argument("--variant", nargs=3, action="append", default=[], metavar=("LABEL", "METHOD", "JSON"),
                    help="a further row: METHOD with EmbedConfig overrides JSON (after --embed), named LABEL; "
                         "the keys 'bits' and 'seeds' (lists) replace --bits / --seeds for that row")
    ap.add_argument("--bits", nargs="+", type=int, default=[32])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--epochs", type=int, default=8)
    ap.add_argument("--message-seed", type=int, default=1000, help="messages are drawn reproducibly from this seed "
                    "+ the cell's seed, the same for every method (a fair comparison)")
    ap.add_argument("--message-weight", type=float, default=None)
    ap.add_argument("--bare", action="store_true", help="embed the SH-0 model without cameras (see docstring)")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    ap.add_argument("--tag", default=None)
    ap.add_argument("--deadline-s", type=float, default=None, help="start no new cell after this many seconds")
    ap.add_argument("--image-attacks", nargs="*", default=list(PAPER_IMAGE), choices=PAPER_IMAGE, metavar="NAME",
                    help=f"subset of the image attacks (default all: {' '.join(PAPER_IMAGE)}; none: no value)")
    ap.add_argument("--model-attacks", nargs="*", default=list(MODEL), choices=MODEL, metavar="NAME",
                    help=f"subset of the model attacks (default all: {' '.join(MODEL)})")
    ap.add_argument("--sizes", nargs="*", type=float, default=list(SIZES), help="render-size factors (default: "
                    "0.5 1.5 2 3)")
    ap.add_argument("--eval-views", type=int, default=None, help="evaluate on this many evenly spaced held-out "
                    "views (default: all)")
    ap.add_argument("--embed", default=None, help="further EmbedConfig overrides for every method, as JSON "
                    "(applied after the method's own, e.g. '{\"novel_views\": 1.0}')")
    return ap.parse_args()


def _scene(args, dev):
    """(model, embedding views, held-out views, background); no photos (embedding needs none)."""
    from gsw.camera import load_inria_cameras, save_inria_cameras
    from gsw.eval.grid import default_grid_scene, load_grid_scene
    from gsw.io.spz import load_spz, save_spz

    if args.scene == "builtin":
        s = default_grid_scene(size=args.size, views=24)
        return s.gaussians.to(dev), s.cameras, s.eval_cameras, s.background
    white = (1.0, 1.0, 1.0)
    if args.train_seconds is not None:
        from power_lego import png_dataset, train_lego  # benchmarks/power_lego.py, beside this script

        opts = argparse.Namespace(size=800, iterations=12000, train_seconds=args.train_seconds)
        g, train_set, test_set, args.trained = train_lego(opts, png_dataset(args.data, args.work), dev)
        return g.to(dev), train_set.cameras, test_set.cameras, white
    if args.model.suffix == ".spz":
        return (load_spz(args.model).to(dev), load_inria_cameras(args.cameras), load_inria_cameras(args.eval_cameras),
                white)
    s = load_grid_scene(args.model, args.data, white=True, downscale=args.downscale)
    g = s.gaussians
    if args.prepare is not None:
        args.prepare.mkdir(parents=True, exist_ok=True)
        save_spz(g, args.prepare / "lego.spz")
        g = load_spz(args.prepare / "lego.spz")
        save_inria_cameras(s.cameras, args.prepare / "train_cameras.json")
        save_inria_cameras(s.eval_cameras, args.prepare / "eval_cameras.json")
    return g.to(dev), s.cameras, s.eval_cameras, white


def _novel_cameras(g, cameras):
    """24 viewpoints at elevations the orbit/hemisphere did not sample, azimuths between the cameras."""
    from gsw.camera import orbit_cameras
    from gsw.mark.views import content_bounds

    centre, _ = content_bounds(g)
    dist = float(torch.stack([(c.center.double().cpu() - centre).norm() for c in cameras]).median())
    c0 = cameras[0]
    return [cam for k, el in enumerate((-15.0, 15.0, 60.0))
            for cam in orbit_cameras(centre.tolist(), dist, 8, width=c0.width, height=c0.height, elevation_deg=el,
                                     fov_x_deg=math.degrees(c0.fov_x), azimuth_offset_deg=22.5 + 15.0 * k)]


def _bit_acc(dec, images, bits) -> float:
    with torch.no_grad():
        return sum(float(((dec.decode_image(im[None].clamp(0, 1))[0] > 0).float().cpu() == bits.cpu()).float().mean())
                   for im in images) / len(images)


def _renders(g, cams, bg):
    from gsw.render.rasterize import rasterize

    with torch.no_grad():
        return [rasterize(g, c, background=bg).image.clamp(0, 1) for c in cams]


def _psnr(a, b) -> float:
    from gsw.metrics.image import psnr

    return sum(float(psnr(x, y)) for x, y in zip(a, b)) / len(a)


def _evaluate(res, g, eval_cams, novel, bg, bits_n, dec, args) -> dict:
    from gsw.attacks.presets import IMAGE_ATTACKS, MODEL_ATTACKS
    from gsw.eval.report import evaluate_watermark
    from gsw.mark.detect import verify

    rep = evaluate_watermark(res.gaussians, g, eval_cams, res.message, num_bits=bits_n, background=bg,
                             image_attacks={n: IMAGE_ATTACKS[n] for n in args.image_attacks},
                             model_attacks={n: MODEL_ATTACKS[n] for n in args.model_attacks}, lpips_net="alex",
                             decoder=dec)
    out = dict(psnr=rep.psnr, ssim=rep.ssim, lpips=rep.lpips, clean=rep.clean.bit_accuracy,
               clean_detected=rep.clean.detected_views, unmarked=rep.unmarked.bit_accuracy,
               image={k: v.bit_accuracy for k, v in rep.image_attacks.items()},
               model={k: v.bit_accuracy for k, v in rep.model_attacks.items()},
               clean_raw=_bit_acc(dec, _renders(res.gaussians, eval_cams, bg), res.message))
    embed_size = (eval_cams[0].height, eval_cams[0].width)
    out["sizes"] = {}
    for s in args.sizes:
        imgs = _renders(res.gaussians, [c.scaled(s) for c in eval_cams], bg)
        v = verify(imgs, res.message, num_bits=bits_n, decoder=dec, embed_size=embed_size)
        out["sizes"][f"{s:g}x"] = dict(raw=_bit_acc(dec, imgs, res.message), read=sum(v.bit_accuracy) / len(imgs))
    if novel:
        marked, plain = _renders(res.gaussians, novel, bg), _renders(g, novel, bg)
        out["novel"] = dict(bit_accuracy=_bit_acc(dec, marked, res.message), psnr=_psnr(marked, plain),
                            min_view=min(_bit_acc(dec, [m], res.message) for m in marked))
    return out


def _bare(res, g, bg, dec, seed: int = 1234) -> dict:
    """A bare model: 24 random viewpoints around the content (not the embedding ones), 512 and 256 px."""
    from gsw.mark.views import ViewSampler, ViewSamplerConfig

    cfg = ViewSamplerConfig(modes=(("orbit", 1.0),), size_range=(1.0, 1.0), base_size=512, elevation_deg=(-85, 85))
    cams = ViewSampler(g, None, cfg, seed=seed).sample_many(24)
    out = {}
    for size in (512, 256):
        cs = [c.scaled(size / 512) for c in cams]
        marked, plain = _renders(res.gaussians, cs, bg), _renders(g, cs, bg)
        out[f"{size}px"] = dict(bit_accuracy=_bit_acc(dec, marked, res.message), psnr=_psnr(marked, plain))
    return out


def _config(args, method: str, seed: int, bg, overrides: dict | None = None):
    import dataclasses

    from gsw.eval.grid import method_config
    from gsw.mark.embed import EmbedConfig
    from gsw.mark.loss import LossWeights, lpips_weights

    from gsw.eval.grid import apply_overrides

    weights = lpips_weights("alex") if args.message_weight is None else lpips_weights(
        "alex", LossWeights(message=args.message_weight))
    base = EmbedConfig(lpips_net="alex", weights=weights)
    cfg = method_config(method, base)
    if args.embed:
        cfg = apply_overrides(cfg, json.loads(args.embed))
    if overrides:
        cfg = apply_overrides(cfg, overrides)
    epochs = (overrides or {}).get("epochs", args.epochs)  # a row may set its own
    return dataclasses.replace(cfg, epochs=epochs, seed=seed, background=bg)


def main() -> int:
    import gsw
    from gsw.attacks.model import reduce_sh
    from gsw.device import resolve_device
    from gsw.mark.detect import load_decoder_for
    from gsw.mark.embed import embed
    from gsw.mark.message import as_message

    args = parse_args()
    start = time.perf_counter()
    dev = resolve_device(args.device)
    g, cams, eval_cams, bg = _scene(args, dev)
    if args.eval_views is not None:
        eval_cams = [eval_cams[i * len(eval_cams) // args.eval_views] for i in range(args.eval_views)]
    if args.bare:
        g = reduce_sh(g, 0)
    novel = None if args.bare else _novel_cameras(g, cams)
    tag = args.tag or f"{args.scene}{'_bare' if args.bare else ''}"
    results = dict(scene=args.scene, bare=args.bare, gaussians=len(g), train_views=len(cams), eval_views=len(eval_cams),
                   size=[cams[0].width, cams[0].height], trained=getattr(args, "trained", None),
                   settings={k: str(v) for k, v in vars(args).items()},
                   machine=dict(device=str(dev), gpu=torch.cuda.get_device_name(dev) if dev.type == "cuda" else None,
                                torch=torch.__version__, python=platform.python_version(), gsw=gsw.__version__),
                   cells=[])
    args.out.mkdir(parents=True, exist_ok=True)
    rows = [(m, m, {}) for m in args.methods] + [(label, m, json.loads(js)) for label, m, js in args.variant]
    for label, method, overrides in rows:
        row_bits, row_seeds = overrides.pop("bits", args.bits), overrides.pop("seeds", args.seeds)
        readout = overrides.pop("readout", "direct")
        for bits_n in row_bits:
            for seed in row_seeds:
                if args.deadline_s and time.perf_counter() - start > args.deadline_s:
                    results["stopped"] = f"deadline before {label} {bits_n} bits seed {seed}"
                    break
                cfg = _config(args, method, seed, bg, overrides)
                dec = load_decoder_for(bits_n, None, dev)
                if readout == "klein":
                    from gsw.decoder import KleinReadout

                    dec = KleinReadout(dec).to(dev).eval()
                if dev.type == "cuda":
                    torch.cuda.synchronize(dev)
                t0 = time.perf_counter()
                message = as_message(None, bits_n, seed=args.message_seed + seed)  # public: the same for every method
                res = embed(g, None if args.bare else cams, message=message, num_bits=bits_n, config=cfg,
                            decoder=dec, progress=False)
                if dev.type == "cuda":
                    torch.cuda.synchronize(dev)
                cell = dict(method=label, base_method=method, overrides=overrides, readout=readout, bits=bits_n,
                            seed=seed,
                            embed_s=time.perf_counter() - t0,
                            timings=res.timings, gaussians_after=len(res.gaussians),
                            train_bit_accuracy=sum(res.bit_accuracy) / len(res.bit_accuracy),
                            train_psnr=sum(res.psnr) / len(res.psnr),
                            final_message_weight=res.history[-1]["message_weight"])
                cell.update(_bare(res, g, bg, dec) if args.bare
                            else _evaluate(res, g, eval_cams, novel, bg, bits_n, dec, args))
                results["cells"].append(cell)
                (args.out / f"robust_wild_{tag}.json").write_text(json.dumps(results, indent=1) + "\n")
                print(json.dumps(cell), flush=True)
    (args.out / f"robust_wild_{tag}.json").write_text(json.dumps(results, indent=1) + "\n")
    (args.out / f"robust_wild_{tag}.md").write_text(markdown(results) + "\n")
    print(markdown(results))
    return 0


def markdown(results: dict) -> str:
    """The cells as one table (bit accuracies in %)."""
    if results["bare"]:
        lines = ["| method | bits | seed | 512 px bits / PSNR | 256 px bits / PSNR | embed s |", "|---|---|---|---|---|---|"]
        for c in results["cells"]:
            lines.append(f"| {c['method']} | {c['bits']} | {c['seed']} | {100 * c['512px']['bit_accuracy']:.1f} / "
                         f"{c['512px']['psnr']:.2f} | {100 * c['256px']['bit_accuracy']:.1f} / {c['256px']['psnr']:.2f} | "
                         f"{c['embed_s']:.0f} |")
        return "\n".join(lines)
    cells = results["cells"]
    if not cells:
        return "(no cells)"
    img, mod, sizes = list(cells[0]["image"]), list(cells[0]["model"]), list(cells[0]["sizes"])
    head = (["method", "bits", "seed", "PSNR", "SSIM", "LPIPS", "clean"] + img + mod
            + [f"{s} raw/read" for s in sizes] + ["novel bits / PSNR / min", "embed s"])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in cells:
        row = [c["method"], str(c["bits"]), str(c["seed"]), f"{c['psnr']:.2f}", f"{c['ssim']:.4f}", f"{c['lpips']:.4f}",
               f"{100 * c['clean']:.1f}"]
        row += [f"{100 * c['image'][k]:.1f}" for k in img] + [f"{100 * c['model'][k]:.1f}" for k in mod]
        row += [f"{100 * c['sizes'][s]['raw']:.1f}/{100 * c['sizes'][s]['read']:.1f}" for s in sizes]
        n = c["novel"]
        row += [f"{100 * n['bit_accuracy']:.1f} / {n['psnr']:.2f} / {100 * n['min_view']:.0f}", f"{c['embed_s']:.0f}"]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
