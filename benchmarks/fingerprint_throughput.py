"""Per-recipient fingerprints (#26): recipients per hour, quality per recipient, `gsw scan` images/s.

For one scene (the built-in scene, or a lego INRIA model with the NeRF-synthetic views: every 8th view
held out) and 32-bit messages: the once-per-scene set-up (FGD) once, then recipients fine-tuned K at a
time (:func:`gsw.fingerprint.batched.finetune_batch`) for each K of ``--batch``; per recipient the bit
accuracy and PSNR (against the original model's renders) on the held-out views. One-at-a-time
``gsw.embed`` (the whole pipeline per recipient) is the baseline. Then ``gsw scan``'s in-process path
(:func:`gsw.fingerprint.scan.scan_sources`) over held-out renders of the copies saved as PNG.

Recipients per hour = 3600 x recipients / fine-tune seconds (the set-up, done once per scene, is reported
apart). Writes ``benchmarks/results/<tag>.json`` (or ``--out``).

Usage:
    python benchmarks/fingerprint_throughput.py --scene builtin --size 256 --batch 1 4 --recipients 4
    python benchmarks/fingerprint_throughput.py --scene lego --model build/train_lego/x_model --batch 1 4 8
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _scene(args, dev):
    """(model, training cameras, held-out cameras, background, images or None)."""
    from gsw.scenes import default_cameras, default_scene

    if args.scene == "builtin":
        sc = default_scene(width=args.size, height=args.size, n_cameras=args.views, device=dev)
        step = 360.0 / args.views
        held = default_cameras(args.held_out, args.size, args.size, azimuth_offset_deg=step / 2)
        return sc.gaussians, sc.cameras, held, tuple(float(v) for v in sc.background), None
    from gsw.data import load_inria_model, load_nerf_synthetic

    model = load_inria_model(args.model)
    size = args.size or model.cameras[0].width
    train = load_nerf_synthetic(args.data, "train", downscale=800 / size)
    test = load_nerf_synthetic(args.data, "test", downscale=800 / size)
    return (model.gaussians.to(dev), train.cameras, test.cameras, (1.0, 1.0, 1.0),
            [im.to(dev) for im in train.images])


@torch.no_grad()
def _held_out(copy, original, cams, bg, message, dec):
    """(bit accuracy per view, PSNR per view) of one copy on the held-out views."""
    from gsw.decoder.dwt import ll_subband
    from gsw.metrics.image import psnr
    from gsw.render.rasterize import rasterize

    accs, psnrs = [], []
    for cam in cams:
        a = rasterize(original, cam, background=bg).image.clamp(0, 1)
        b = rasterize(copy, cam, background=bg).image.clamp(0, 1)
        bits = (dec(ll_subband(b[None]))[0] > 0).float().cpu()
        accs.append(float((bits == message).float().mean()))
        psnrs.append(float(psnr(b, a)))
    return accs, psnrs


def _summary(rows):
    accs = [min(r["held_out_bits"]) for r in rows]
    ps = [sum(r["held_out_psnr"]) / len(r["held_out_psnr"]) for r in rows]
    means = [sum(r["held_out_bits"]) / len(r["held_out_bits"]) for r in rows]
    return dict(recipients=len(rows), mean_bit_accuracy=sum(means) / len(means), min_recipient_bit_accuracy=min(means),
                min_view_bit_accuracy=min(accs), mean_psnr=sum(ps) / len(ps), min_recipient_psnr=min(ps),
                recipients_ge_99_and_37=sum(m >= 0.99 and p >= 37 for m, p in zip(means, ps)))


def bench_batches(args, dev, g, cams, held, bg, images, cfg):
    from gsw.fingerprint.batched import finetune_batch
    from gsw.fingerprint.plan import Recipient, assign_messages
    from gsw.fingerprint.shared import prepare_scene, worker_scene
    from gsw.mark.message import message_from_hex

    t0 = time.perf_counter()
    shared = prepare_scene(g, cams, num_bits=args.bits, config=cfg, images=images, device=dev)
    _sync(dev)
    setup_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    ws = worker_scene(shared, dev)
    _sync(dev)
    worker_s = time.perf_counter() - t0
    out, copies = dict(setup_s=setup_s, worker_setup_s=worker_s, stats=shared.stats, batches={}), []
    start = time.perf_counter()
    for k in args.batch:
        if time.perf_counter() - start > args.budget_s:
            print(f"budget reached before K={k}", flush=True)
            break
        people = assign_messages([Recipient(f"k{k}_{i}") for i in range(max(k, args.recipients))], args.bits)
        rows, fine = [], 0.0
        for i in range(0, len(people), k):
            chunk = people[i:i + k]
            msgs = torch.stack([message_from_hex(p.message, args.bits) for p in chunk])
            _sync(dev)
            t0 = time.perf_counter()
            res = finetune_batch(ws, [p.name for p in chunk], msgs)
            _sync(dev)
            fine += time.perf_counter() - t0
            for r, m in zip(res, msgs):
                accs, ps = _held_out(r.gaussians.to(dev), g, held, bg, m, ws.loss.decoder)
                rows.append(dict(name=r.name, train_bits=r.bit_accuracy, train_psnr=r.psnr, held_out_bits=accs,
                                 held_out_psnr=ps))
                copies.append((r.gaussians, m))
        out["batches"][k] = dict(finetune_s=fine, recipients_per_hour=3600 * len(rows) / fine,
                                 peak_gib=(torch.cuda.max_memory_allocated(dev) / 2**30 if dev.type == "cuda" else None),
                                 summary=_summary(rows), rows=rows)
        print(json.dumps({k: {x: y for x, y in out["batches"][k].items() if x != "rows"}}, indent=1), flush=True)
    return out, copies


def bench_baseline(args, dev, g, cams, held, bg, images, cfg):
    """One-at-a-time gsw.embed (set-up included, as a separate `gsw embed` per recipient)."""
    from gsw.mark.embed import embed
    from gsw.mark.message import random_message

    rows, total = [], 0.0
    for i in range(args.baseline):
        m = random_message(args.bits, seed=1000 + i)
        _sync(dev)
        t0 = time.perf_counter()
        res = embed(g, cams, message=m, num_bits=args.bits, images=images, config=cfg, progress=False)
        _sync(dev)
        total += time.perf_counter() - t0
        from gsw.decoder.zoo import load_decoder

        accs, ps = _held_out(res.gaussians, g, held, bg, m, load_decoder(args.bits).to(dev))
        rows.append(dict(held_out_bits=accs, held_out_psnr=ps, timings=res.timings))
    return dict(seconds=total, recipients_per_hour=3600 * len(rows) / total, summary=_summary(rows), rows=rows)


def bench_scan(args, dev, copies, held, bg):
    """`gsw scan` in one process over PNG renders of the copies (held-out views), CPU and ``dev``."""
    from gsw.data.images import write_image
    from gsw.fingerprint.scan import scan_sources
    from gsw.mark.message import message_to_hex
    from gsw.registry import open_registry, shipped_decoder_sha256
    from gsw.render.rasterize import rasterize

    tmp = Path(tempfile.mkdtemp())
    reg = open_registry(tmp / "marks.sqlite")
    sha = shipped_decoder_sha256(args.bits)
    reg.add_many([dict(label=f"r{i}", message=message_to_hex(m), num_bits=args.bits, decoder_sha256=sha)
                  for i, (_, m) in enumerate(copies)])
    marks = reg.list()
    paths = []
    with torch.no_grad():
        for i in range(args.scan_images):
            g, _ = copies[i % len(copies)]
            img = rasterize(g.to(dev), held[i % len(held)], background=bg).image.clamp(0, 1)
            paths.append(tmp / f"img{i:04d}.png")
            write_image(paths[-1], img.cpu())
    out = {}
    for where in ["cpu"] + (["cuda"] if dev.type == "cuda" else []):
        n = len(paths) if where == "cuda" else min(len(paths), args.scan_cpu_images)
        t0 = time.perf_counter()
        rows = scan_sources(paths[:n], marks, device=None if where == "cpu" else torch.device(where))
        sec = time.perf_counter() - t0
        truth = [f"r{i % len(copies)}" for i in range(n)]
        out[where] = dict(images=n, seconds=sec, images_per_s=n / sec, marks=len(marks),
                          identified_right=sum(r.identified == t for r, t in zip(rows, truth)),
                          identified_wrong=sum(bool(r.identified) and r.identified != t for r, t in zip(rows, truth)),
                          size=f"{held[0].width}x{held[0].height}")
        print(json.dumps({where: out[where]}), flush=True)
    reg.close()
    return out


def main() -> int:
    import gsw
    from gsw.device import resolve_device
    from gsw.mark.embed import EmbedConfig
    from gsw.mark.loss import lpips_weights

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=["builtin", "lego"], default="builtin")
    ap.add_argument("--model", help="lego INRIA model folder (benchmarks/train_lego.py)")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "lego"))
    ap.add_argument("--size", type=int, default=None, help="builtin: render size (default 256); lego: default 800")
    ap.add_argument("--views", type=int, default=24, help="builtin: training views")
    ap.add_argument("--held-out", type=int, default=8, help="builtin: held-out views (between the training views)")
    ap.add_argument("--bits", type=int, default=32)
    ap.add_argument("--epochs", type=int, default=8)
    ap.add_argument("--lpips", choices=["alex", "vgg", "none"], default="alex")
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--recipients", type=int, default=4, help="recipients per batch size (at least K)")
    ap.add_argument("--baseline", type=int, default=1, help="one-at-a-time gsw.embed runs")
    ap.add_argument("--scan-images", type=int, default=64)
    ap.add_argument("--scan-cpu-images", type=int, default=32)
    ap.add_argument("--scan-only", type=int, default=0, metavar="MARKS",
                    help="only time `gsw scan` over renders of the unmarked model against MARKS random marks")
    ap.add_argument("--budget-s", type=float, default=1e9, help="no new batch size after this many seconds")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--tag", default=None)
    ap.add_argument("--out", default=None, help="result folder (default benchmarks/results)")
    args = ap.parse_args()
    if args.scene == "builtin":
        args.size = args.size or 256
    dev = resolve_device(args.device)
    lp = None if args.lpips == "none" else args.lpips
    g, cams, held, bg, images = _scene(args, dev)
    cfg = EmbedConfig(epochs=args.epochs, background=bg, lpips_net=lp, weights=lpips_weights(lp))
    res = dict(scene=args.scene, gaussians=len(g), size=f"{cams[0].width}x{cams[0].height}", views=len(cams),
               held_out_views=len(held), settings=vars(args))
    if args.scan_only:
        from gsw.mark.message import random_message

        copies = [(g, random_message(args.bits, seed=i)) for i in range(args.scan_only)]
        res["scan"] = bench_scan(args, dev, copies, held, bg)
        return _write(args, dev, res)
    res["baseline"] = bench_baseline(args, dev, g, cams, held, bg, images, cfg) if args.baseline else None
    if res["baseline"]:
        print(json.dumps({"baseline": {x: y for x, y in res["baseline"].items() if x != "rows"}}), flush=True)
    res["fingerprint"], copies = bench_batches(args, dev, g, cams, held, bg, images, cfg)
    res["scan"] = bench_scan(args, dev, copies, held, bg) if args.scan_images else None
    return _write(args, dev, res)


def _write(args, dev, res) -> int:
    import gsw

    res["machine"] = dict(device=str(dev), gpu=torch.cuda.get_device_name(dev) if dev.type == "cuda" else None,
                          cpu=platform.processor(), threads=torch.get_num_threads(), torch=torch.__version__,
                          python=platform.python_version(), gsw=gsw.__version__,
                          date=time.strftime("%Y-%m-%d %H:%M:%S"))
    tag = args.tag or f"fingerprint_{args.scene}_{dev.type}"
    out = Path(args.out) if args.out else ROOT / "benchmarks" / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{tag}.json").write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
