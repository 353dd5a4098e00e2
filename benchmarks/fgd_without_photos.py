"""FGD phase 1 with and without the training photos (lego): what each error weighting prunes, and the copies after.

Three weightings of :func:`gsw.mark.fgd.fgd_prune` on one trained lego model: the photos (the paper's), no photos
(gsw's rule: the model's alpha) and the earlier no-photo rule (the model's own render in place of the photos, which
is what passing the render as ``images`` still does). For each: Gaussians pruned, the pruned model's held-out PSNR
against the original; then (``--epochs`` > 0) a fingerprint job of ``--recipients`` recipients with that FGD (the
pool's default recipe, K = recipients) and every copy's held-out bit accuracy and PSNR against the original.

Usage (the 2026-11-27 CPU run: lego 200x200 trained 240 s, 4 epochs, ~15 min on 2 cores):
    python benchmarks/fgd_without_photos.py --size 200 --train-seconds 240 --epochs 4 --out results.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    import gsw
    from gsw.data import load_inria_model
    from gsw.data.loaders import load_nerf_synthetic
    from gsw.decoder.zoo import load_decoder
    from gsw.device import resolve_device
    from gsw.fingerprint.batched import pool_config
    from gsw.fingerprint.plan import Recipient
    from gsw.mark.fgd import fgd_prune
    from gsw.registry import open_registry
    from gsw.render.rasterize import rasterize
    from gsw.train import TrainConfig, train

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from fingerprint_throughput import held_out_scores

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "lego"))
    ap.add_argument("--size", type=int, default=200)
    ap.add_argument("--train-seconds", type=float, default=240.0)
    ap.add_argument("--epochs", type=int, default=4, help="fingerprint passes (0: pruning only)")
    ap.add_argument("--recipients", type=int, default=2)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    dev = resolve_device(args.device)
    bg = (1.0, 1.0, 1.0)
    down = 800 / args.size
    tr = load_nerf_synthetic(args.data, "train", downscale=down, background=bg)
    te = load_nerf_synthetic(args.data, "test", downscale=down, background=bg)
    t0 = time.perf_counter()
    res = train(tr, config=TrainConfig(max_train_time_s=args.train_seconds, device=str(dev), seed=0), progress=False,
                background=bg)
    g = res.gaussians.to(dev)
    out = dict(size=args.size, gaussians=len(g), iterations=res.iterations, train_s=time.perf_counter() - t0,
               torch=torch.__version__, device=str(dev), date=time.strftime("%Y-%m-%d %H:%M:%S %Z"), rows=[])
    print(f"trained: {len(g)} Gaussians, {res.iterations} iterations", flush=True)
    with torch.no_grad():
        orig = [rasterize(g, c, background=bg).image.clamp(0, 1) for c in te.cameras]
        own = [rasterize(g, c, background=bg).image for c in tr.cameras]
    photos = [im.to(dev) for im in tr.images]
    dec = load_decoder(32).to(dev)

    def held_out(model, message=None):
        """(mean bit accuracy or None, mean PSNR) on the held-out views."""
        accs, ps = held_out_scores(model, orig, te.cameras, bg, message, dec)
        return (sum(accs) / len(accs) if accs else None), sum(ps) / len(ps)

    recipients = [Recipient(f"r{i}", f"{(0x0f1e2d3c * (i + 1)) & 0xffffffff:08x}") for i in range(args.recipients)]
    for name, images in (("photos", photos), ("no photos (alpha)", None), ("own render (earlier rule)", own)):
        pruned, rep = fgd_prune(g, tr.cameras, images, background=bg)
        row = dict(weighting=name, pruned=rep.num_removed, pruned_model_psnr=held_out(pruned)[1])
        if args.epochs > 0:
            tmp = Path(tempfile.mkdtemp(prefix="gsw-fgd-"))
            t0 = time.perf_counter()
            with open_registry(tmp / "marks.sqlite") as reg:
                job = gsw.fingerprint(g, tr.cameras, recipients, tmp / "copies", reg, num_bits=32,
                                      config=pool_config(epochs=args.epochs, background=bg), images=images,
                                      batch_size=len(recipients), device=dev, use_ray=False, progress=False)
                messages = {m.label: m.message.float() for m in reg.list()}
            row["job_s"] = time.perf_counter() - t0
            row["copies"] = []
            for r in job.recipients:
                bits, p = held_out(load_inria_model(r.folder).gaussians.to(dev), messages[r.name])
                row["copies"].append(dict(name=r.name, train_psnr=r.psnr, held_out_bits=bits, held_out_psnr=p))
        out["rows"].append(row)
        print(json.dumps(row), flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
