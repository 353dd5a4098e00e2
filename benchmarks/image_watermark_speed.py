"""Speed of the image watermark (``gsw.embed_image``'s optimisation) per photo, on CPU or CUDA.

Times ``gsw.mark.refine.watermark_images`` with ``ImageEmbedConfig``'s defaults (or the given settings) on
bsds500/val photos at full size (481x321 or 321x481), one photo at a time (what ``gsw embed-image`` does) and
in batches (throughput), against the shipped whitened decoder, and records the bit accuracy read back after
8-bit rounding.

    python benchmarks/image_watermark_speed.py --device cuda --photos 8 --batch 8 --out speed.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import torch

from gsw.decoder.dwt import ll_subband
from gsw.decoder.pretrain.data import load_images
from gsw.decoder.pretrain.evaluation import same_size_groups
from gsw.decoder.zoo import load_decoder
from gsw.mark.refine import ImageEmbedConfig, watermark_images

ROOT = Path(__file__).resolve().parents[1]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run(photos: list[torch.Tensor], k: int, cfg: ImageEmbedConfig, batch: int, device: torch.device) -> dict:
    """Seconds per photo and read-back accuracy for photos embedded ``batch`` at a time (same-size groups;
    a short untimed run first pays for CUDA/cuDNN start-up)."""
    dec = load_decoder(k).to(device).eval().requires_grad_(False)
    gen = torch.Generator().manual_seed(cfg.seed)
    accs: list[float] = []
    chunks = [[photos[i] for i in g] for g in same_size_groups(photos, batch)]
    warm_x = torch.stack(chunks[0]).to(device).float() / 255.0  # CUDA/cuDNN start-up, not timed
    watermark_images(dec, warm_x, torch.zeros(len(chunks[0]), k, device=device), psnr=cfg.psnr, steps=8,
                     attack_every=1, amp=device.type == "cuda")
    total = 0.0
    for n, chunk in enumerate(chunks):
        x = torch.stack(chunk).to(device).float() / 255.0
        m = torch.randint(0, 2, (len(chunk), k), generator=gen).float().to(device)
        _sync(device)
        t0 = time.perf_counter()
        y = watermark_images(dec, x, m, psnr=cfg.psnr, steps=cfg.steps, attack_every=cfg.attack_every,
                             lr=cfg.lr, seed=cfg.seed + n, amp=device.type == "cuda")
        _sync(device)
        total += time.perf_counter() - t0
        y = (y * 255).round() / 255
        with torch.no_grad():
            accs += ((dec(ll_subband(y)) > 0).float() == m).float().mean(1).tolist()
    return {"bits": k, "batch": batch, "photos": len(photos), "chunks": len(chunks),
            "seconds_per_photo": total / len(photos), "bit_accuracy_after_8bit": sum(accs) / len(accs),
            "photos_all_bits_right": sum(a == 1.0 for a in accs)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "bsds500"))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--bits", type=int, nargs="+", default=[32])
    ap.add_argument("--photos", type=int, default=4)
    ap.add_argument("--batch", type=int, nargs="+", default=[1], help="photos optimised together")
    ap.add_argument("--steps", type=int, default=ImageEmbedConfig.steps)
    ap.add_argument("--psnr", type=float, default=ImageEmbedConfig.psnr)
    ap.add_argument("--threads", type=int, default=None, help="CPU threads (default: torch's)")
    ap.add_argument("--out", default=None, help="write the results as JSON here")
    args = ap.parse_args()
    device = torch.device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = ImageEmbedConfig(psnr=args.psnr, steps=args.steps)
    photos = load_images(Path(args.data) / "val", limit=args.photos)
    res: dict = {"machine": platform.processor() or platform.machine(), "torch": torch.__version__,
                 "device": torch.cuda.get_device_name(device) if device.type == "cuda" else
                 f"CPU, {torch.get_num_threads()} threads", "config": vars(cfg), "runs": []}
    for k in args.bits:
        for b in args.batch:
            r = run(photos, k, cfg, b, device)
            res["runs"].append(r)
            print(json.dumps(r), flush=True)
    if args.out:
        tmp = Path(f"{args.out}.tmp")
        tmp.write_text(json.dumps(res, indent=1) + "\n")
        tmp.replace(args.out)


if __name__ == "__main__":
    main()
