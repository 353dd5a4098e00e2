"""Power of the calibrated detector on lego (issue #22): detection at 1e-6 of held-out renders at 0.5x-3x.

Steps (one process, GPU recommended; the JSON is rewritten after every step, so a run stopped early keeps
what it measured):

1. train 3DGS on NeRF-synthetic lego (every 8th view held out; INRIA recipe compressed to
   ``--iterations``, stopped at ``--train-seconds``), white background, ``--size`` pixels;
2. control: the UNMARKED model's held-out renders at 1x against the message (known size and search);
3. embed a message of each ``--bits`` length (fixed seed; steps 2-5 per length) with
   :class:`gsw.mark.embed.EmbedConfig`'s defaults (8 epochs, FGD, exp mask; ``--lpips`` picks another LPIPS
   network, ``--epochs`` fewer epochs);
4. held-out views: the 13 held-out lego cameras and ``--orbit`` orbit cameras (elevations 20/35/50 deg,
   azimuths between the training views') -- none of them used for embedding; rendered at each of
   ``--scales`` times the embedding size (intrinsics scaled; 1x first), the scales in order while the time
   budget ``--max-seconds`` allows (a scale is skipped when the previous one's time says it would not fit,
   a later bit length when its embedding would not);
5. per view, the evidence of :func:`gsw.verify` (:func:`gsw.mark.evidence.score_messages`, decoded on the
   GPU) with the embedding size known (one reading at that size) and unknown (the scale search), by the
   rule for a RANDOM message (``exact_*``, the default since 2026-11-25: the signed-rank randomization
   test of the most confident reading; sets: the pooled logits tested once) and, for comparison, the rule
   for a CHOSEN message (``known_size`` / ``search``: the calibrated null model, weighted Bonferroni over
   the readings; sets: Hommel) and the search with equal weights (``search_equal_weights``, the rule
   before 2026-11-25); sets of 10 views = every cyclic window of 10 consecutive held-out views; the
   detection rate at 1e-6 of each (and of the exact test with unit weights, ``exact_sign_known_size``:
   the number of matching bits), the median and largest p-values, per-view matches, chosen factors and
   a summary of each view's logits at the known size (median |logit|, the |logit| ranks of the wrong
   bits, the logits themselves to 2 decimals).

Writes JSON to ``--out`` (default ``benchmarks/results/power_lego.json``) and, when ``$OUT`` is set, a copy
there.

    PYTHONPATH=. python benchmarks/power_lego.py --data ../shared/data/lego --device cuda

The photos may be PNG (as in ``../shared/data/lego``) or WebP (smaller, for a size-limited transfer):
``--pack-webp DIR`` writes such a copy here; a ``--data`` folder of WebP photos is converted back to PNG
under ``--work`` before training.  Needs kornia (the 3DGS training's SSIM term).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
SCALES = (1.0, 0.5, 1.5, 2.0, 3.0)  # the embedding size first: it matters most when time runs short
FPR = 1e-6
SET_SIZE = 10


# ------------------------------------------------------------------------------------------- data
def pack_webp(data: Path, dest: Path, quality: int = 95) -> None:
    """Writes ``data``'s transforms files and its photos as WebP (RGBA kept) under ``dest``."""
    from PIL import Image

    if not any(data.glob("transforms_*.json")):
        raise FileNotFoundError(f"no transforms_*.json in {data}")
    for t in data.glob("transforms_*.json"):
        (dest / t.name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(t, dest / t.name)
    for png in sorted(data.rglob("*.png")):
        out = dest / png.relative_to(data).with_suffix(".webp")
        out.parent.mkdir(parents=True, exist_ok=True)
        Image.open(png).save(out, "WEBP", quality=quality)
    print(f"wrote {dest}: {sum(f.stat().st_size for f in dest.rglob('*') if f.is_file()) / 2**20:.1f} MiB")


def png_dataset(data: Path, work: Path) -> Path:
    """``data`` itself when its photos are PNG; when they are WebP, a copy with PNG photos under ``work``."""
    from PIL import Image

    webps = sorted(data.rglob("*.webp"))
    if not webps:
        return data
    for t in data.glob("transforms_*.json"):
        work.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(t, work / t.name)
    for w in webps:
        out = work / w.relative_to(data).with_suffix(".png")
        if not out.is_file():
            out.parent.mkdir(parents=True, exist_ok=True)
            Image.open(w).save(out)
    print(f"converted {len(webps)} WebP photos to PNG under {work}", flush=True)
    return work


def held_out_cameras(test_cams, n_orbit: int):
    """The held-out lego cameras plus ``n_orbit`` orbit cameras of the same intrinsics (white-box novel views)."""
    from gsw.camera import orbit_cameras

    ref = test_cams[0]
    radius = float(ref.center.double().norm())
    fov = math.degrees(ref.fov_x)
    cams = list(test_cams)
    if n_orbit <= 0:
        return cams
    per_ring = max(1, n_orbit // 3)
    for r, elev in enumerate((20.0, 35.0, 50.0)):
        cams += orbit_cameras((0.0, 0.0, 0.0), radius, per_ring, width=ref.width, height=ref.height,
                              elevation_deg=elev, fov_x_deg=fov, azimuth_offset_deg=7.0 + 5.0 * r)
    return cams


def render(g, cams, bg):
    from gsw.render.rasterize import rasterize

    with torch.no_grad():
        return [rasterize(g, c, background=bg).image.clamp(0, 1) for c in cams]


def train_lego(args, data: Path, dev):
    from gsw.data.loaders import load_nerf_synthetic
    from gsw.train import TrainConfig, train

    down = 800 / args.size
    train_set = load_nerf_synthetic(data, "train", downscale=down)
    test_set = load_nerf_synthetic(data, "test", downscale=down)
    cfg = TrainConfig.scaled(args.iterations, max_train_time_s=args.train_seconds, device=str(dev), seed=0)
    res = train(train_set, config=cfg, progress=False, test_set=test_set, background=(1.0, 1.0, 1.0))
    info = {"iterations": res.iterations, "train_time_s": res.train_time_s, "gaussians": len(res.gaussians),
            "test_psnr": (res.test_metrics or {}).get("psnr")}
    print("trained", info, flush=True)
    return res.gaussians, train_set, test_set, info


# ------------------------------------------------------------------------------------------- scoring
def windows(n: int) -> list[list[int]]:
    """Every cyclic window of :data:`SET_SIZE` consecutive views (all views when fewer)."""
    size = min(SET_SIZE, n)
    return [[(i + j) % n for j in range(size)] for i in range(n)]


def rates(p_values: np.ndarray, set_p: np.ndarray | None = None) -> dict:
    """Detection rate at :data:`FPR` of single views and of every cyclic window of :data:`SET_SIZE` views
    (``set_p``; default: Hommel's combination of the views' p-values, the rule for chosen messages)."""
    from gsw.stats import hommel_combined_p_value

    p = np.asarray(p_values, dtype=np.float64)
    n = len(p)
    sets = (np.array([float(hommel_combined_p_value(p[w])) for w in windows(n)]) if set_p is None
            else np.asarray(set_p, dtype=np.float64))
    return {"single": float((p <= FPR).mean()), "single_detected": int((p <= FPR).sum()), "views": n,
            "sets_of_10": float((sets <= FPR).mean()), "sets_detected": int((sets <= FPR).sum()), "sets": n,
            "median_p": float(np.median(p)), "max_p": float(p.max()), "median_set_p": float(np.median(sets)),
            "max_set_p": float(sets.max())}


def exact(readings, message: np.ndarray, weighting: str = "rank") -> dict:
    """The random-message rule (:mod:`gsw.mark.randomization`): views and pooled windows of views."""
    from gsw.mark.evidence import score_messages

    views = score_messages(readings, message[None], weighting=weighting).p_values[:, 0]
    sets = [score_messages([readings[i] for i in w], message[None], weighting=weighting).combined[0]
            for w in windows(len(readings))]
    return rates(views, np.array(sets)) | {"p": views.tolist()}


def logit_summary(readings, message: np.ndarray) -> dict:
    """Per view (one reading each): median |logit|, the |logit| ranks (1 = least confident) of the wrong
    bits, and the logits (2 decimals)."""
    from gsw.mark.randomization import bit_weights

    logits = np.stack([r.logits[0].numpy() for r in readings])  # [V, k]
    ranks = bit_weights(logits, "rank")
    wrong = (logits > 0) != (message[None] == 1)
    return {"median_abs_logit": np.round(np.median(np.abs(logits), 1), 3).tolist(),
            "wrong_bit_ranks": [ranks[v][wrong[v]].tolist() for v in range(len(logits))],
            "logits": np.round(logits, 2).tolist()}


def evaluate(imgs, decoder, null, message: np.ndarray, embed_size: tuple[int, int]) -> dict:
    """The exact (random-message) rule, and for comparison the calibrated (chosen-message) rule with the known
    size, the weighted search and the equal-weight search, for views and sets."""
    from gsw.mark.evidence import score_messages
    from gsw.mark.scales import read_images
    from gsw.stats import bonferroni_p_value

    known_r = read_images(imgs, decoder, embed_size=embed_size)
    search_r = read_images(imgs, decoder)
    known = score_messages(known_r, message[None], null, origin="chosen")
    search = score_messages(search_r, message[None], null, origin="chosen")
    k = len(message)
    per_reading = [null.p_values(r.bits.numpy().astype(np.int8), message, np.asarray(r.factors)) for r in search_r]
    equal = np.array([float(bonferroni_p_value(p)) for p in per_reading])
    matches = [(r.bits.numpy().astype(np.int8) == message).sum(-1) for r in search_r]
    return {
        "render_size": list(imgs[0].shape[-2:]),
        "bit_accuracy_known_size": float(known.matches[:, 0].mean() / k),
        "bit_accuracy_search": float(search.matches[:, 0].mean() / k),
        "exact_known_size": exact(known_r, message), "exact_search": exact(search_r, message),
        "exact_sign_known_size": exact(known_r, message, "sign"),  # the count of matching bits, exact for random
        "known_size": rates(known.p_values[:, 0]), "search": rates(search.p_values[:, 0]),
        "search_equal_weights": rates(equal), "logits_known_size": logit_summary(known_r, message),
        "search_factors": [round(f, 4) for f in search_r[0].factors],
        "most_confident_reads_most_bits": float(np.mean([m[int(r.confidence.argmax())] == m.max()
                                                         for m, r in zip(matches, search_r)])),
        "views": {"matches_known_size": known.matches[:, 0].tolist(),
                  "matches_per_search_factor": [m.tolist() for m in matches],
                  "most_confident_factor": [round(r.factors[int(r.confidence.argmax())], 4) for r in search_r],
                  "p_known_size": known.p_values[:, 0].tolist(), "p_search": search.p_values[:, 0].tolist(),
                  "p_search_equal_weights": equal.tolist()},
    }


def summary(res: dict) -> str:
    ex_k, ex_s = res["exact_known_size"], res["exact_search"]
    return (f"bits {res['bit_accuracy_known_size']:.4f} | EXACT single known/search {ex_k['single_detected']}/"
            f"{ex_s['single_detected']} of {ex_k['views']}, sets {ex_k['sets_detected']}/{ex_s['sets_detected']}, "
            f"max p {ex_k['max_p']:.2g}/{ex_s['max_p']:.2g} | CALIBRATED single known/search/equal "
            f"{res['known_size']['single_detected']}/{res['search']['single_detected']}/"
            f"{res['search_equal_weights']['single_detected']} of {res['known_size']['views']} | sets "
            f"{res['known_size']['sets_detected']}/{res['search']['sets_detected']}/"
            f"{res['search_equal_weights']['sets_detected']} | median p {res['known_size']['median_p']:.2g}/"
            f"{res['search']['median_p']:.2g}/{res['search_equal_weights']['median_p']:.2g}")


def write(out: dict, path: Path) -> None:
    """The results so far, atomically, to ``path`` and (when ``$OUT`` is set) a copy there."""
    from gsw._atomic import atomic_write

    text = json.dumps(out, indent=1) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as f:
        f.write(text)
    if os.environ.get("OUT"):
        Path(os.environ["OUT"]).mkdir(parents=True, exist_ok=True)
        with atomic_write(Path(os.environ["OUT"], path.name), "w") as f:
            f.write(text)


# ------------------------------------------------------------------------------------------- main
def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "lego",
                    help="lego folder (transforms_train.json + PNG or WebP photos)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "power_lego.json")
    ap.add_argument("--work", type=Path, default=ROOT / "build" / "power_lego_png",
                    help="where WebP photos are converted to PNG")
    ap.add_argument("--pack-webp", type=Path, default=None, metavar="DIR",
                    help="only write a WebP copy of --data to DIR (for a size-limited transfer) and exit")
    ap.add_argument("--size", type=int, default=800, help="embedding render size (lego: 800 = native)")
    ap.add_argument("--iterations", type=int, default=12000)
    ap.add_argument("--train-seconds", type=float, default=75.0)
    ap.add_argument("--bits", type=int, nargs="+", default=[32, 48],
                    help="message lengths, one embedding each, in order (later ones skipped when out of time)")
    ap.add_argument("--epochs", type=int, default=None, help="default: EmbedConfig's")
    ap.add_argument("--lpips", default="vgg", choices=["alex", "vgg", "none"])
    ap.add_argument("--orbit", type=int, default=24, help="extra held-out orbit views (multiple of 3)")
    ap.add_argument("--scales", type=float, nargs="+", default=list(SCALES))
    ap.add_argument("--max-seconds", type=float, default=330.0,
                    help="time budget of the whole run: later scales / bit lengths are skipped when they would not "
                         "fit (the first scale of each embedded length is always measured)")
    ap.add_argument("--device", default="auto")
    return ap.parse_args()


def main() -> None:
    args = parse_args()
    if args.pack_webp is not None:
        pack_webp(args.data, args.pack_webp)
        return
    from gsw.device import resolve_device
    from gsw.mark.evidence import CONFIDENT_SHARE

    t0 = time.perf_counter()
    dev = resolve_device(args.device)
    out: dict = {"device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor(),
                 "torch": torch.__version__, "python": platform.python_version(),
                 "settings": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
                 "fpr": FPR, "confident_share": CONFIDENT_SHARE, "runs": {}, "skipped_bits": []}
    g, train_set, test_set, out["train"] = train_lego(args, png_dataset(args.data, args.work), dev)
    cams = held_out_cameras(test_set.cameras, args.orbit)
    out |= {"held_out_views": len(cams), "embed_size": [cams[0].height, cams[0].width]}
    write(out, args.out)
    embed_s = 0.0
    for i, bits in enumerate(args.bits):
        if i > 0 and time.perf_counter() - t0 + 1.5 * embed_s > args.max_seconds:
            out["skipped_bits"].append(bits)
            print(f"{bits} bits skipped (time budget)", flush=True)
            continue
        out["runs"][f"k{bits}"] = run = {}
        embed_s = run_bits(args, bits, g, train_set, cams, dev, run, lambda: write(out, args.out), t0)
    out["seconds"] = time.perf_counter() - t0
    write(out, args.out)
    print(f"done in {out['seconds']:.0f} s; wrote {args.out}")


def run_bits(args, bits: int, g, train_set, cams, dev, run: dict, save, t0: float) -> float:
    """Control, embedding and every scale for one bit length; fills ``run`` (saved after each step).
    Returns the embedding's seconds."""
    from gsw.decoder.zoo import load_decoder
    from gsw.mark import EmbedConfig, embed
    from gsw.mark.evidence import shipped_null_model
    from gsw.mark.loss import lpips_weights
    from gsw.mark.message import random_message

    bg = (1.0, 1.0, 1.0)
    message = random_message(bits, seed=2222)  # fixed: the run is reproducible
    m = message.numpy().astype(np.int8)
    decoder = load_decoder(bits, device=dev)
    null = shipped_null_model(bits)
    null.check_decoder(decoder)
    size = (cams[0].height, cams[0].width)
    run["unmarked_control_1x"] = evaluate(render(g, cams, bg), decoder, null, m, size)
    print(f"k={bits} unmarked control 1x:", summary(run["unmarked_control_1x"]), flush=True)
    save()
    lp = None if args.lpips == "none" else args.lpips
    cfg = EmbedConfig(background=bg, lpips_net=lp, weights=lpips_weights(lp))
    if args.epochs is not None:
        cfg.epochs = args.epochs
    t1 = time.perf_counter()
    res = embed(g, train_set.cameras, message=message, num_bits=bits,
                images=[im.to(dev) for im in train_set.images], config=cfg, progress=False)
    run["embed"] = {"seconds": time.perf_counter() - t1, "gaussians": len(res.gaussians),
                    "config": {"epochs": cfg.epochs, "lpips": lp, "fgd": cfg.fgd, "mask": cfg.mask},
                    "train_bit_accuracy": sum(res.bit_accuracy) / len(res.bit_accuracy),
                    "train_psnr": sum(res.psnr) / len(res.psnr)}
    print(f"k={bits} embedded in {run['embed']['seconds']:.1f} s, train-view bit accuracy "
          f"{run['embed']['train_bit_accuracy']:.4f}", flush=True)
    run |= {"scales": {}, "skipped_scales": []}
    save()
    last: tuple[float, float] | None = None  # (scale, seconds) of the previous scale
    for s in args.scales:
        elapsed = time.perf_counter() - t0
        # the first scale is always measured (the JSON is saved after it); later ones only while they fit
        if last is not None and (elapsed > args.max_seconds
                                 or elapsed + last[1] * max(1.0, (s / last[0]) ** 2) > args.max_seconds):
            run["skipped_scales"].append(s)
            print(f"k={bits} {s:g}x skipped (time budget: {elapsed:.0f} s spent of {args.max_seconds:.0f})",
                  flush=True)
            continue
        t2 = time.perf_counter()
        imgs = render(res.gaussians, [c.scaled(s) for c in cams], bg)
        run["scales"][f"{s:g}x"] = evaluate(imgs, decoder, null, m, size)
        del imgs
        last = (s, time.perf_counter() - t2)
        run["scales"][f"{s:g}x"]["seconds"] = last[1]
        print(f"k={bits} {s:g}x ({last[1]:.1f} s):", summary(run["scales"][f"{s:g}x"]), flush=True)
        save()
    return run["embed"]["seconds"]


if __name__ == "__main__":
    main()
