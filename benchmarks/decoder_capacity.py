"""What limits the pre-training pair: the shipped decoders' capacity vs the encoder (CPU).

Three checks on bsds500/val photos at full size, each against the shipped *raw* decoder
(``load_decoder(k).decoder``, before whitening), PSNR fixed by rescaling the residual, 8-bit rounding:

1. ``psnr``: a pre-training encoder (``--encoder-run``: a ``gsw decoder train`` run holding ``encoder_ft``)
   at several PSNRs. If accuracy does not grow with the watermark's strength, the errors are in the code the
   encoder writes, not noise.
2. ``direct``: each photo's pixels optimised against the decoder (Adam, residual projected to the PSNR):
   how many bits the decoder can read at all.
3. ``tile``: one periodic tile per message (side ``--tile`` at LL2 resolution, tiled and upsampled as
   ``TemplateEncoder`` does), optimised on a few photos and read on unseen ones: an image-agnostic code.
4. ``refine`` (``--checks refine``, GPU): the optimisation encoder (``gsw.mark.refine.watermark_images``,
   what ``gsw.embed_image`` runs) measured like a pre-training pair: each photo's residual, from noise, refined
   by ``gsw.mark.refine.refine_residual`` (cosine Adam, binary cross-entropy, PSNR ``--psnr`` kept) for
   each ``--refine STEPS:EVERY`` (EVERY > 0: every EVERY-th step also goes through the next training noise
   layer, ``GpuAttacks``, differentiable JPEG; 0: the clean loss only), against the raw decoder or, with
   ``--decoder whitened``, the shipped decoder exactly as ``gsw.extract`` reads it, then
   ``eval_attacks`` over ``--refine-photos`` val photos x ``--refine-msgs`` messages with every training noise
   layer (real JPEG; with ``--paper-attacks`` also the paper's fixed-strength attacks), with each photo's
   clean accuracy and share of saturated (0 or 255) pixel values (photo index: val photos sorted by file
   name). The results are written after each setting.

    python benchmarks/decoder_capacity.py --encoder-run out/decoders/A --out benchmarks/results/decoder_capacity.json
    python benchmarks/decoder_capacity.py --checks refine --device cuda --refine 1000:4 1000:0 --out refine.json
    python benchmarks/decoder_capacity.py --checks refine --device cuda --bits 32 --decoder whitened --out k32.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from gsw.attacks.layers import paper_attacks, training_noise_layers
from gsw.decoder.dwt import ll_subband
from gsw.decoder.hidden import scale_to_psnr
from gsw.decoder.pretrain.data import load_images
from gsw.decoder.pretrain.encoders import embed_scaled, load_run_encoder
from gsw.decoder.pretrain.evaluation import eval_attacks
from gsw.metrics.image import psnr as psnr_db
from gsw.decoder.zoo import load_decoder
from gsw.mark.refine import SCHEDULES, watermark_images
from gsw.stats import bootstrap_ci95

ROOT = Path(__file__).resolve().parents[1]


def _accuracy(dec, y: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """Per-image bit accuracy [B] of 8-bit-rounded images y [B,3,H,W] against messages m [B,k]."""
    y = (y.clamp(0, 1) * 255).round() / 255
    return ((dec(ll_subband(y)) > 0).float() == m).float().mean(1)


@torch.no_grad()
def psnr_sweep(run: Path, k: int, photos: list[torch.Tensor], levels: list[float], msgs_per_photo: int = 4) -> dict:
    enc, cfg = load_run_encoder(run, k)
    dec = load_decoder(k).decoder
    out = {}
    for level in levels:
        gen = torch.Generator().manual_seed(0)
        acc, ps = [], []
        for img in photos:
            x = (img.float() / 255)[None].expand(msgs_per_photo, -1, -1, -1).contiguous()
            m = torch.randint(0, 2, (msgs_per_photo, k), generator=gen).float()
            y = embed_scaled(enc, x, m, level, cfg.enc_down)
            ps.append(psnr_db((y.clamp(0, 1) * 255).round() / 255, x))
            acc.append(_accuracy(dec, y, m))
        out[str(level)] = {"bit_acc": float(torch.cat(acc).mean()), "psnr": float(torch.cat(ps).mean())}
    return out


def direct(k: int, photos: list[torch.Tensor], psnr: float, steps: int) -> dict:
    dec = load_decoder(k).decoder
    gen = torch.Generator().manual_seed(0)
    accs = []
    for img in photos:
        x = (img.float() / 255)[None]
        m = torch.randint(0, 2, (1, k), generator=gen).float()
        r = (torch.randn(x.shape, generator=gen) * 1e-3).requires_grad_(True)
        opt = torch.optim.Adam([r], lr=0.01)
        for _ in range(steps):
            y = (x + scale_to_psnr(r, psnr)).clamp(0, 1)
            loss = F.binary_cross_entropy_with_logits(dec(ll_subband(y)), m)
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            accs.append(float(_accuracy(dec, x + scale_to_psnr(r, psnr), m)))
    return {"bit_acc": sum(accs) / len(accs), "per_photo": accs, "photos": len(photos), "steps": steps}


def _tiled(tile: torch.Tensor, x: torch.Tensor, psnr: float) -> torch.Tensor:
    t = tile.shape[-1]
    h, w = x.shape[-2:]
    hs, ws = -(-h // 4), -(-w // 4)
    pat = tile.repeat(1, 1, -(-hs // t), -(-ws // t))[..., :hs, :ws]
    d = F.interpolate(pat, size=(hs * 4, ws * 4), mode="bilinear", align_corners=False)[..., :h, :w]
    return x + scale_to_psnr(d, psnr)


def tile(k: int, fit: list[torch.Tensor], unseen: list[torch.Tensor], side: int, psnr: float, steps: int,
         messages: int) -> dict:
    dec = load_decoder(k).decoder
    gen = torch.Generator().manual_seed(0)
    fit_x = [(p.float() / 255)[None] for p in fit]
    unseen_x = [(p.float() / 255)[None] for p in unseen]
    acc = {"fit": [], "unseen": []}
    for _ in range(messages):
        m = torch.randint(0, 2, (1, k), generator=gen).float()
        p = (torch.randn(1, 3, side, side, generator=gen) * 0.01).requires_grad_(True)
        opt = torch.optim.Adam([p], lr=0.02)
        for _ in range(steps):
            loss = sum(F.binary_cross_entropy_with_logits(dec(ll_subband(_tiled(p, x, psnr).clamp(0, 1))), m)
                       for x in fit_x)
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            for name, xs in (("fit", fit_x), ("unseen", unseen_x)):
                acc[name] += [float(_accuracy(dec, _tiled(p, x, psnr), m)) for x in xs]
    return {"bit_acc_fit_photos": sum(acc["fit"]) / len(acc["fit"]),
            "bit_acc_unseen_photos": sum(acc["unseen"]) / len(acc["unseen"]),
            "side": side, "messages": messages, "steps": steps, "fit_photos": len(fit), "unseen_photos": len(unseen)}


def refine(k: int, photos: list[torch.Tensor], psnr: float, steps: int, every: int, msgs: int, lr: float,
           margin: float, batch: int, device: torch.device, schedule: str = "cosine", seed: int = 1,
           whitened: bool = False, paper: bool = False) -> dict:
    """The optimisation encoder (``gsw.mark.refine.watermark_images``: residuals from noise refined for
    ``steps``) against the shipped raw or whitened decoder, evaluated like a pair."""
    model = load_decoder(k).to(device).eval()
    dec = model if whitened else model.decoder
    batches = itertools.count()

    def embed(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        return watermark_images(dec, x, m, psnr=psnr, steps=steps, attack_every=every, lr=lr,
                                margin=margin, schedule=schedule, seed=1000 * seed + next(batches),
                                amp=device.type == "cuda")

    t0 = time.perf_counter()
    training = training_noise_layers()
    attacks = {**training, **paper_attacks()} if paper else training
    r = eval_attacks(embed, dec, photos, attacks, k, msgs, seed=seed, device=device,
                     images_per_batch=batch, per_image=True)
    layers = {n: v for n, v in r["bit_acc"].items() if n != "identity" and n in training}
    clean = r["per_image"]["identity"]
    errors = sorted(((1.0 - a) * k * msgs for a in clean), reverse=True)  # wrong bits per photo
    return {"bits": k, "decoder": "whitened" if whitened else "raw", "steps": steps, "attack_every": every,
            "lr": lr, "margin": margin, "schedule": schedule, "seed": seed, "psnr_target": psnr,
            "bf16": device.type == "cuda", "clean": r["bit_acc"]["identity"], "worst_layer": min(layers.values()),
            "bit_acc": r["bit_acc"], "bit_acc_std": r["bit_acc_std"], "psnr": r["psnr"], "pairs": r["n"],
            "photos": len(photos), "photos_all_bits_right": sum(a == 1.0 for a in clean),
            "photo_bootstrap_95": bootstrap_ci95(clean, seed=seed),
            "wrong_bits_share_of_worst_10_photos": sum(errors[:10]) / max(1e-9, sum(errors)),
            "per_photo_clean": [round(a, 4) for a in clean],
            "per_photo_saturated": [round(float(((p == 0) | (p == 255)).float().mean()), 4) for p in photos],
            "wall_s": round(time.perf_counter() - t0, 1)}


def _write(path: str, res: dict) -> None:
    tmp = f"{path}.tmp"
    Path(tmp).write_text(json.dumps(res, indent=1) + "\n")
    os.replace(tmp, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "bsds500"))
    ap.add_argument("--encoder-run", default=None, help="`gsw decoder train` run with encoder_ft (for the sweep)")
    ap.add_argument("--psnr-levels", type=float, nargs="+", default=[30.0, 28.0, 26.0, 24.0])
    ap.add_argument("--sweep-photos", type=int, default=50)
    ap.add_argument("--direct-photos", type=int, nargs=2, default=[6, 12], metavar=("K48", "K64"))
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--tile", type=int, default=16)
    ap.add_argument("--checks", nargs="+", default=["direct", "tile"], choices=["direct", "tile", "refine"],
                    help="checks to run (the PSNR sweep runs when --encoder-run is given)")
    ap.add_argument("--device", default="cpu", help="device of the refine check (the others run on the CPU)")
    ap.add_argument("--bits", type=int, default=64, help="bit length of the refine check")
    ap.add_argument("--refine", nargs="+", default=["1000:4"], metavar="STEPS:EVERY",
                    help="refine settings: Adam steps and attack period (0: clean loss only)")
    ap.add_argument("--refine-photos", type=int, default=100)
    ap.add_argument("--refine-msgs", type=int, default=4, help="messages per photo")
    ap.add_argument("--refine-batch", type=int, default=25, help="photos refined together")
    ap.add_argument("--refine-lr", type=float, default=0.3)
    ap.add_argument("--refine-margin", type=float, default=0.0)
    ap.add_argument("--refine-schedule", default="cosine", choices=list(SCHEDULES))
    ap.add_argument("--refine-seed", type=int, default=1, help="messages, attacks and starting noise")
    ap.add_argument("--decoder", default="raw", choices=["raw", "whitened"],
                    help="refine check against the raw decoder or the shipped whitened one (what gsw.extract reads)")
    ap.add_argument("--psnr", type=float, default=30.0, help="PSNR (dB) of the watermarks (direct, tile, refine)")
    ap.add_argument("--paper-attacks", action="store_true",
                    help="refine check: also the paper's fixed-strength attacks (worst_layer stays over training layers)")
    ap.add_argument("--out", default=None, help="write the results as JSON here")
    args = ap.parse_args()
    try:
        settings = [tuple(int(v) for v in s.split(":")) for s in args.refine]
        assert all(len(t) == 2 and t[0] >= 0 and t[1] >= 0 for t in settings)
    except (ValueError, AssertionError):
        ap.error(f"--refine takes STEPS:EVERY pairs of integers >= 0, got {args.refine}")
    device = torch.device(args.device)
    if device.type == "cpu":
        torch.set_num_threads(2)
    val = load_images(Path(args.data) / "val")
    if not val:
        raise SystemExit(f"no photos in {Path(args.data) / 'val'}")
    t0 = time.perf_counter()
    res: dict = {"machine": platform.processor() or platform.machine(), "torch": torch.__version__,
                 "psnr_target": args.psnr}
    if device.type == "cuda":
        res["device"] = torch.cuda.get_device_name(device)
    if args.encoder_run:
        res["psnr_sweep"] = {str(k): psnr_sweep(Path(args.encoder_run), k, val[: args.sweep_photos],
                                                args.psnr_levels) for k in (48, 64)}
        print(json.dumps(res["psnr_sweep"]), flush=True)
    if "direct" in args.checks:
        res["direct"] = {str(k): direct(k, val[:n], args.psnr, args.steps) for k, n in zip((48, 64), args.direct_photos)}
        print(json.dumps({k: v["bit_acc"] for k, v in res["direct"].items()}), flush=True)
    if "tile" in args.checks:
        res["tile_64"] = tile(64, val[:4], val[4:8], args.tile, args.psnr, args.steps, messages=3)
        print(json.dumps(res["tile_64"]), flush=True)
    if "refine" in args.checks:
        res[f"refine_{args.bits}"] = []
        for steps, every in settings:
            r = refine(args.bits, val[: args.refine_photos], args.psnr, steps, every, args.refine_msgs,
                       args.refine_lr, args.refine_margin, args.refine_batch, device, args.refine_schedule,
                       args.refine_seed, whitened=args.decoder == "whitened", paper=args.paper_attacks)
            res[f"refine_{args.bits}"].append(r)
            print(f"refine {steps}:{every}  clean {r['clean']:.4f}  worst layer {r['worst_layer']:.4f}  "
                  f"{json.dumps({n: round(v, 4) for n, v in r['bit_acc'].items()})}  {r['wall_s']} s", flush=True)
            if args.out:
                _write(args.out, res)
    res["wall_s"] = round(time.perf_counter() - t0, 1)
    if args.out:
        _write(args.out, res)


if __name__ == "__main__":
    main()
