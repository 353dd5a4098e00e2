"""Per-recipient fingerprints (#26): recipients per GPU-hour and every recipient's held-out quality, as a sweep.

For one scene (the built-in scene, or lego: trained here for ``--train-seconds`` or loaded from ``--model``,
the NeRF-synthetic views with every 8th held out) and 32-bit secret messages, each *setting* of the sweep
runs a whole :func:`gsw.fingerprint` job in this process (a fresh output folder and registry): the
once-per-scene set-up (FGD, reported apart), then the recipients through a pool of K slots with or without
per-recipient early stopping (:mod:`gsw.fingerprint.stopping`), each copy written atomically and registered.
Recipients per hour = 3600 x recipients / the job's fine-tune seconds (everything after the set-up: the
worker scene, the pool's steps, slot refills, scoring, writes and registry records). Then every copy is read
back from its folder and measured on the held-out views (never used by the job): bit accuracy per view
(decoded from its render) and PSNR against the original model's render. A recipient *meets* the target when
its mean held-out bit accuracy is >= 99 % and its mean held-out PSNR >= 37 dB.

A setting is one string of space-separated ``key=value``: ``k`` (slots), ``n`` (recipients), ``epochs`` (step
cap in passes), ``mw`` (message weight), ``lpips`` (alex/vgg/none), ``stop`` (an
:meth:`~gsw.fingerprint.stopping.EarlyStop.parse` string, or ``none``), ``freeze`` (comma-separated parameter
groups kept fixed, trained without the exponential mask: ``freeze=f_rest`` is the grid's ``freeze-rest`` and the
pool's default since 2026-11-29; ``freeze=none``: the paper's freeze and mask, every group trained with the
exponential mask; with ``l1=1 mse=0 fgd=1`` the paper's recipe), ``views``
(``EmbedConfig.novel_views``: the share of steps rendered from a sampled viewpoint, default 0) and ``bank``
(``EmbedConfig.view_bank``: viewpoints sampled once per job for those steps, default 0: fresh ones), ``l1`` / ``mse``
(``LossWeights.l1`` / ``.mse``) and ``fgd`` (``EmbedConfig.fgd``, 1 or 0); those three default to the pool's
(:func:`gsw.fingerprint.batched.pool_config`: ``l1=0 mse=35 fgd=0`` since 2026-11-29, ``l1=1 mse=0 fgd=1`` before).
The JSON (``--out``/``<tag>.json``) is rewritten after every setting; ``--budget-s`` stops starting new settings.
``--scan-only MARKS`` only times ``gsw scan`` (:func:`gsw.fingerprint.scan.scan_sources`) over held-out renders of
the unmarked model. ``--exports`` also reads every copy on the held-out views after what a leaker's viewer export
does to it (:data:`EXPORTS`: SH degree 0, ``.splat`` and ``.spz`` round trips through gsw's codecs).

Usage (lego on one GPU, ~4.5 min with the training; the lego photos in ``--data``):
    python benchmarks/fingerprint_throughput.py --scene lego --data DIR --train-seconds 60 --device cuda --out OUT
CPU smoke test:
    python benchmarks/fingerprint_throughput.py --scene builtin --size 64 --views 6 --held-out 2 \\
        --setting "k=2 n=3 epochs=1 lpips=none stop=none" --setting "k=2 n=3 epochs=2 lpips=none stop=min_steps=2"
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

#: The lego sweep, most informative first. A recipient's optimisation does not depend on K (only the time
#: does), so settings differ in quality only through the stopping rule and the message weight.
LEGO_SWEEP = [
    "k=8 n=12 stop=min_steps=96,window=16,margin=1,psnr_target=37.4,adapt=1.25,confirm=0.998",
    "k=16 n=24 stop=min_steps=96,window=24,margin=2,psnr_target=37.4,adapt=1.25,confirm=0.998",
    "k=8 n=12 stop=min_steps=96,window=16,margin=1",
    "k=8 n=12 mw=0.1 stop=min_steps=96,window=16,margin=1,confirm=0.998",
    "k=8 n=8 stop=none",
]
BUILTIN_SWEEP = ["k=4 n=8 stop=none", "k=4 n=8 stop=min_steps=48,window=8,margin=1"]


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _train_lego(args, dev):
    from gsw.data.loaders import load_nerf_synthetic
    from gsw.train import TrainConfig, train

    down = 800 / args.size
    train_set = load_nerf_synthetic(args.data, "train", downscale=down, background=(1.0, 1.0, 1.0))
    test_set = load_nerf_synthetic(args.data, "test", downscale=down, background=(1.0, 1.0, 1.0))
    t0 = time.perf_counter()
    cfg = TrainConfig(max_train_time_s=args.train_seconds, device=str(dev),  # INRIA recipe, cut by time
                      seed=getattr(args, "train_seed", 0))
    res = train(train_set, config=cfg, progress=False, test_set=test_set, background=(1.0, 1.0, 1.0))
    info = dict(iterations=res.iterations, seconds=time.perf_counter() - t0, gaussians=len(res.gaussians),
                test_psnr=(res.test_metrics or {}).get("psnr"))
    print("trained", json.dumps(info), flush=True)
    return res.gaussians, train_set, test_set, info


def _scene(args, dev):
    """(model, embedding cameras, held-out cameras, background, images or None, training info)."""
    from gsw.scenes import default_cameras, default_scene

    if args.scene == "builtin":
        sc = default_scene(width=args.size, height=args.size, n_cameras=args.views, device=dev)
        offset = 180.0 / args.views if args.held_out_azimuth is None else args.held_out_azimuth
        held = [cam for el in args.held_out_elevation for cam in default_cameras(
            args.held_out, args.size, args.size, azimuth_offset_deg=offset, elevation_deg=el)]
        return sc.gaussians, sc.cameras, held, tuple(float(v) for v in sc.background), None, None
    if args.model is None:
        g, train_set, test_set, info = _train_lego(args, dev)
        return g, train_set.cameras, test_set.cameras, (1.0, 1.0, 1.0), [im.to(dev) for im in train_set.images], info
    from gsw.data import load_inria_model, load_nerf_synthetic

    model = load_inria_model(args.model)
    train = load_nerf_synthetic(args.data, "train", downscale=800 / args.size)
    test = load_nerf_synthetic(args.data, "test", downscale=800 / args.size)
    return (model.gaussians.to(dev), train.cameras, test.cameras, (1.0, 1.0, 1.0),
            [im.to(dev) for im in train.images], None)


def parse_setting(text: str) -> dict:
    """A sweep setting (see the module docstring) as a dict with every key."""
    from gsw.fingerprint.stopping import EarlyStop

    out = dict(k=4, n=8, epochs=8, mw=None, lpips="alex", stop=None, freeze="", views=0.0, bank=0, l1=None, mse=None,
               fgd=None, text=text)
    for token in text.split():
        key, sep, value = token.partition("=")
        if not sep or key not in out or key == "text":
            keys = " ".join(k for k in out if k != "text")
            raise SystemExit(f"--setting {text!r}: bad token {token!r} (keys: {keys})")
        if key == "stop":
            out[key] = None if value == "none" else EarlyStop.parse(value)
        elif key in ("lpips", "freeze"):
            out[key] = value
        else:
            out[key] = float(value) if key in ("mw", "views", "l1", "mse") else int(value)
    return out


@torch.no_grad()
def held_out_scores(copy, originals, cams, bg, message=None, dec=None):
    """(bit accuracy per view, PSNR per view) of one copy on the held-out views ``cams``, against the original
    model's renders ``originals`` ([3, H, W] each, clamped); without ``message`` only the PSNRs (accuracies ``[]``).
    Used by this script, ``fingerprint_multi_gpu.py`` and ``fgd_without_photos.py``."""
    from gsw.decoder.dwt import ll_subband
    from gsw.metrics.image import psnr
    from gsw.render.rasterize import rasterize

    accs, psnrs = [], []
    with torch.no_grad():
        for cam, a in zip(cams, originals):
            b = rasterize(copy, cam, background=bg).image.clamp(0, 1)
            if message is not None:
                bits = (dec(ll_subband(b[None]))[0] > 0).float().cpu()
                accs.append(float((bits == message).float().mean()))
            psnrs.append(float(psnr(b, a)))
    return accs, psnrs


@torch.no_grad()
def original_logits(g, cams, bg, dec) -> torch.Tensor:
    """[V, k] the decoder's logits of the input model's renders of ``cams`` (message-free): what every
    recipient's fine-tune starts from."""
    from gsw.render.rasterize import rasterize

    return torch.stack([dec.decode_image(rasterize(g, cam, background=bg).image.clamp(0, 1)[None])[0].float().cpu()
                        for cam in cams])


def head_start(logits: torch.Tensor, message: torch.Tensor) -> dict:
    """How far a message is from what the decoder reads on the input model's renders (``original_logits``):
    the mean signed logit towards the message, the share of (view, bit) pairs already read right, and the bits
    whose mean logit over the views points away from the message (a diagnostic of hard messages)."""
    signed = logits * (2 * message.float() - 1)
    return dict(original_signed_logit=float(signed.mean()), original_matching=float((signed > 0).float().mean()),
                original_opposed_bits=int((signed.mean(0) < 0).sum()))


#: ``--exports``: name -> the model attack (:mod:`gsw.attacks.model`) a copy is read after.
EXPORTS = {"sh0": "reduce_sh", "splat": "export_splat", "spz": "export_spz"}


def export_scores(copy, held_orig, held, bg, message, dec) -> dict:
    """Mean held-out bit accuracy of ``copy`` after each of :data:`EXPORTS`."""
    from gsw.attacks import model as attacks

    out = {}
    for name, fn in EXPORTS.items():
        accs, _ = held_out_scores(getattr(attacks, fn)(copy.to("cpu")).to(copy.means.device), held_orig, held, bg,
                                  message, dec)
        out[name] = sum(accs) / len(accs)
    return out


def _quartiles(values: list[float]) -> list[float]:
    v = sorted(values)
    return [v[round(q * (len(v) - 1))] for q in (0.0, 0.25, 0.5, 0.75, 1.0)]


def _summary(rows: list[dict]) -> dict:
    means = [sum(r["held_out_bits"]) / len(r["held_out_bits"]) for r in rows]
    ps = [sum(r["held_out_psnr"]) / len(r["held_out_psnr"]) for r in rows]
    steps = [r["steps"] for r in rows]
    exports = {name: dict(mean=sum(r["exports"][name] for r in rows) / len(rows),
                          min=min(r["exports"][name] for r in rows),
                          at_least_97=sum(r["exports"][name] >= 0.97 for r in rows))
               for name in (rows[0].get("exports") or {})}
    return dict(recipients=len(rows), exports=exports, mean_bit_accuracy=sum(means) / len(means), min_recipient_bit_accuracy=min(means),
                min_view_bit_accuracy=min(min(r["held_out_bits"]) for r in rows), mean_psnr=sum(ps) / len(ps),
                min_recipient_psnr=min(ps), psnr_quartiles=_quartiles(ps),
                meeting_99_and_37=sum(m >= 0.99 and p >= 37 for m, p in zip(means, ps)),
                meeting_99=sum(m >= 0.99 for m in means), meeting_37=sum(p >= 37 for p in ps),
                mean_steps=sum(steps) / len(steps), min_steps=min(steps), max_steps=max(steps),
                stopped_early=sum(bool(r["stopped_early"]) for r in rows),
                refusals=sum(r.get("refusals") or 0 for r in rows), redraws=sum(r.get("redraws") or 0 for r in rows),
                redrawn_steps=sum(r.get("redrawn_steps") or 0 for r in rows))


def setting_config(setting: dict, bg):
    """The pool's EmbedConfig of a sweep setting (its epochs, LPIPS term, message weight, frozen groups and share
    of sampled viewpoints and their bank)."""
    from dataclasses import replace

    from gsw.fingerprint.batched import pool_config
    from gsw.mark.embed import PAPER_RECIPE
    from gsw.mark.loss import lpips_weights

    lp = None if setting["lpips"] == "none" else setting["lpips"]
    pool = pool_config()
    weights = replace(pool.weights, **{k: setting[k] for k in ("l1", "mse") if setting[k] is not None})
    weights = lpips_weights(lp, weights if setting["mw"] is None else replace(weights, message=setting["mw"]))
    text = setting.get("freeze", "")
    frozen = tuple(name for name in text.split(",") if name and text != "none")
    # "": the pool's default; a group list: the grid's freeze-rest (no exponential mask); "none": the paper's recipe
    paper = {k: PAPER_RECIPE[k] for k in ("freeze", "mask")}
    extra = paper if text == "none" else {"freeze": frozen, "mask": "none"} if frozen else {}
    return pool_config(epochs=setting["epochs"], background=bg, lpips_net=lp, weights=weights,
                       novel_views=setting["views"], view_bank=setting["bank"],
                       fgd=pool.fgd if setting["fgd"] is None else bool(setting["fgd"]), **extra)


def run_setting(args, dev, g, cams, held, held_orig, bg, images, setting: dict) -> dict:
    """One fingerprinting job of the sweep and its held-out measurements (and each message's
    :func:`head_start` on the embedding views)."""
    import gsw
    from gsw.data import load_inria_model
    from gsw.decoder.zoo import load_decoder
    from gsw.registry import open_registry

    cfg = setting_config(setting, bg)
    tmp = Path(tempfile.mkdtemp(prefix="gsw-fp-"))
    names = [f"r{i:03d}" for i in range(setting["n"])]
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    _sync(dev)
    t0 = time.perf_counter()
    with open_registry(tmp / "marks.sqlite") as reg:
        report = gsw.fingerprint(g, cams, names, tmp / "copies", reg, num_bits=args.bits, config=cfg, images=images,
                                 batch_size=setting["k"], early_stop=setting["stop"], device=dev, use_ray=False,
                                 progress=False)
        _sync(dev)
        wall = time.perf_counter() - t0
        messages = {m.label: m.message for m in reg.list()}
    dec = load_decoder(args.bits).to(dev)
    start_logits = original_logits(g, cams, bg, dec)
    rows = []
    for r in report.recipients:
        copy = load_inria_model(r.folder).gaussians.to(dev)
        accs, ps = held_out_scores(copy, held_orig, held, bg, messages[r.name].float(), dec)
        exports = export_scores(copy, held_orig, held, bg, messages[r.name].float(), dec) if args.exports else None
        rows.append(dict(name=r.name, exports=exports, steps=r.steps, stopped_early=r.stopped_early, refusals=r.refusals,
                         redraws=r.redraws, redrawn_steps=r.redrawn_steps,
                         seconds=r.seconds, train_bits=r.bit_accuracy,
                         train_min_bits=r.min_bit_accuracy, train_psnr=r.psnr, probe_bits=r.probe_bit_accuracy,
                         held_out_bits=accs, held_out_psnr=ps,
                         **head_start(start_logits, messages[r.name].cpu())))
    fine = report.timings["finetune"]
    out = dict(setting=setting["text"], k=setting["k"], epochs=setting["epochs"], message_weight=cfg.weights.message,
               lpips=setting["lpips"], freeze=setting["freeze"], novel_views=setting["views"],
               view_bank=setting["bank"], early_stop=None if setting["stop"] is None else vars(setting["stop"]),
               setup_s=report.timings.get("setup"), finetune_s=fine, job_wall_s=wall,
               recipients_per_hour=3600 * len(rows) / fine,
               ms_per_recipient_step=1000 * fine / max(1, sum((r["steps"] or 0) + (r["redrawn_steps"] or 0)
                                                             for r in rows)),
               peak_gib=torch.cuda.max_memory_allocated(dev) / 2**30 if dev.type == "cuda" else None,
               summary=_summary(rows), rows=rows)
    print(json.dumps({x: y for x, y in out.items() if x != "rows"}), flush=True)
    return out


def profile_pool(args, dev, g, cams, bg, images, setting: dict) -> dict:
    """torch.profiler over ``--profile`` steps of one pool of ``k`` slots (after 20 warm-up steps): the device
    time of each labelled phase of a step (``gsw.pool.*``, :meth:`gsw.fingerprint.batched._Pool.step`) and of
    the top operators, the device's busy share of the profiled wall time (union of its kernels' intervals) and the
    operator / kernel counts per step; the table goes to ``<tag>_profile.txt``, and with ``--trace`` a Chrome
    trace of 3 more steps to ``<tag>_trace.json.gz`` (where the device waits for the host)."""
    from torch.profiler import ProfilerActivity, profile

    from gsw.device import deterministic
    from gsw.fingerprint.batched import _Pool
    from gsw.fingerprint.shared import prepare_scene, worker_scene
    from gsw.mark.message import random_message

    cfg = setting_config(setting, bg)
    k = setting["k"]
    with deterministic():
        scene = worker_scene(prepare_scene(g, cams, num_bits=args.bits, config=cfg, images=images, device=dev), dev)
        pool = _Pool(scene, torch.stack([random_message(args.bits, seed=i) for i in range(k)]), k, None)
        for j in range(k):
            pool.fill(j, j)
        for _ in range(20):
            pool.step()
        _sync(dev)
        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
        folder = Path(args.out) if args.out else ROOT / "benchmarks" / "results"
        folder.mkdir(parents=True, exist_ok=True)
        stem = args.tag or f"fingerprint_{args.scene}_{dev.type}"
        t0 = time.perf_counter()
        with profile(activities=acts) as prof:
            for _ in range(args.profile):
                pool.step()
            _sync(dev)
        wall = time.perf_counter() - t0
        if args.trace:
            with profile(activities=acts) as tprof:
                for _ in range(3):
                    pool.step()
                _sync(dev)
            tprof.export_chrome_trace(str(folder / f"{stem}_trace.json.gz"))  # gzipped by the suffix
    busy = _device_busy(prof) if dev.type == "cuda" else None
    events = prof.key_averages()
    dev_us = (lambda e: getattr(e, "device_time_total", 0.0)) if dev.type == "cuda" else (lambda e: e.cpu_time_total)
    phases = {e.key: dev_us(e) / 1e3 / args.profile for e in events if e.key.startswith("gsw.pool.")}
    top = sorted((e for e in events if not e.key.startswith("gsw.pool.")), key=dev_us, reverse=True)[:25]
    table = events.table(sort_by="device_time_total" if dev.type == "cuda" else "cpu_time_total", row_limit=40)
    (folder / f"{stem}_profile.txt").write_text(table)
    out = dict(setting=setting["text"], k=k, steps=args.profile, ms_per_step_wall=1000 * wall / args.profile,
               ms_per_recipient_step_wall=1000 * wall / args.profile / k, phase_device_ms_per_step=phases,
               top_ops_device_ms_per_step={e.key: dev_us(e) / 1e3 / args.profile for e in top},
               aten_ops_per_step=sum(e.count for e in events if e.key.startswith("aten::")) / args.profile)
    if busy is not None:
        out.update(device_busy_share=busy[0], device_kernel_ms_per_step=busy[1] / args.profile,
                   kernels_per_step=busy[2] / args.profile)
    print(json.dumps(out), flush=True)
    return out


def _device_busy(prof) -> tuple[float, float, int]:
    """(share of the profiled window with a kernel running, ms of kernel time as a union, kernels) from the
    device events of a torch.profiler run."""
    spans = sorted((e.time_range.start, e.time_range.end) for e in prof.events()
                   if getattr(e, "device_type", None) is not None and e.device_type.name == "CUDA")
    if not spans:
        return 0.0, 0.0, 0
    union, (a, b) = 0.0, spans[0]
    for s, e in spans[1:]:
        if s > b:
            union += b - a
            a, b = s, e
        else:
            b = max(b, e)
    union += b - a
    window = max(e for _, e in spans) - spans[0][0]
    return union / window, union / 1e3, len(spans)


def bench_baseline(args, dev, g, cams, held, held_orig, bg, images) -> dict:
    """One-at-a-time ``gsw.embed`` (set-up included, as a separate ``gsw embed`` per recipient)."""
    from gsw.decoder.zoo import load_decoder
    from gsw.fingerprint.batched import pool_config
    from gsw.mark.embed import embed
    from gsw.mark.message import random_message

    cfg = pool_config(background=bg, lpips_net="alex")
    rows, total = [], 0.0
    for i in range(args.baseline):
        m = random_message(args.bits, seed=1000 + i)
        _sync(dev)
        t0 = time.perf_counter()
        res = embed(g, cams, message=m, num_bits=args.bits, images=images, config=cfg, progress=False)
        _sync(dev)
        total += time.perf_counter() - t0
        accs, ps = held_out_scores(res.gaussians, held_orig, held, bg, m, load_decoder(args.bits).to(dev))
        rows.append(dict(steps=cfg.epochs * len(cams), stopped_early=False, held_out_bits=accs, held_out_psnr=ps,
                         timings=res.timings))
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
    from gsw.device import resolve_device
    from gsw.render.rasterize import rasterize

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=["builtin", "lego"], default="builtin")
    ap.add_argument("--model", help="lego INRIA model folder (default: train one for --train-seconds)")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "lego"))
    ap.add_argument("--train-seconds", type=float, default=60.0, help="lego training time without --model")
    ap.add_argument("--size", type=int, default=None, help="render size (default: builtin 256, lego 800)")
    ap.add_argument("--views", type=int, default=24, help="builtin: embedding views")
    ap.add_argument("--held-out", type=int, default=8, help="builtin: held-out views (between the embedding views)")
    ap.add_argument("--held-out-azimuth", type=float, default=None,
                    help="builtin: the held-out ring's azimuth offset, degrees (default: half the embedding views' "
                         "spacing, halfway between them)")
    ap.add_argument("--held-out-elevation", type=float, nargs="+", default=[30.0],
                    help="builtin: the held-out rings' elevations, degrees, --held-out views each (default: 30, the "
                         "embedding ring's)")
    ap.add_argument("--bits", type=int, default=32)
    ap.add_argument("--setting", action="append", default=None,
                    help="a sweep setting (repeatable; default: the scene's sweep, see LEGO_SWEEP / BUILTIN_SWEEP)")
    ap.add_argument("--baseline", type=int, default=0, help="one-at-a-time gsw.embed runs (after the sweep)")
    ap.add_argument("--exports", action="store_true",
                    help="also read every copy on the held-out views after SH degree 0, .splat and .spz round trips")
    ap.add_argument("--scan-only", type=int, default=0, metavar="MARKS",
                    help="only time `gsw scan` over renders of the unmarked model against MARKS random marks")
    ap.add_argument("--scan-images", type=int, default=64)
    ap.add_argument("--scan-cpu-images", type=int, default=32)
    ap.add_argument("--profile", type=int, default=0, metavar="STEPS",
                    help="only profile STEPS pool steps of the first setting (torch.profiler; no job is run)")
    ap.add_argument("--trace", action="store_true", help="with --profile: a Chrome trace of 3 more steps")
    ap.add_argument("--no-photos", action="store_true",
                    help="lego: FGD without the photos (as `gsw fingerprint` on a model folder without --images)")
    ap.add_argument("--budget-s", type=float, default=100.0, help="no new setting after this many seconds of sweep")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--tag", default=None)
    ap.add_argument("--out", default=None, help="result folder (default benchmarks/results)")
    args = ap.parse_args()
    args.size = args.size or (800 if args.scene == "lego" else 256)
    settings = [parse_setting(s) for s in (args.setting or (LEGO_SWEEP if args.scene == "lego" else BUILTIN_SWEEP))]
    dev = resolve_device(args.device)
    t_start = time.perf_counter()
    g, cams, held, bg, images, train_info = _scene(args, dev)
    if args.no_photos:
        images = None
    with torch.no_grad():
        held_orig = [rasterize(g, cam, background=bg).image.clamp(0, 1) for cam in held]
    res = dict(scene=args.scene, gaussians=len(g), size=f"{cams[0].width}x{cams[0].height}", views=len(cams),
               held_out_views=len(held), training=train_info, settings=vars(args), machine=_machine(dev),
               sweep=[], baseline=None)
    if args.profile:
        res["profile"] = profile_pool(args, dev, g, cams, bg, images, settings[0])
        _write(args, dev, res)
        return 0
    if args.scan_only:
        from gsw.mark.message import random_message

        res["scan"] = bench_scan(args, dev, [(g, random_message(args.bits, seed=i)) for i in range(args.scan_only)],
                                 held, bg)
        _write(args, dev, res)
        return 0
    start = time.perf_counter()
    for s in settings:
        if time.perf_counter() - start > args.budget_s:
            print(f"budget reached: skipping {s['text']!r}", flush=True)
            res.setdefault("skipped", []).append(s["text"])
            continue
        try:
            res["sweep"].append(run_setting(args, dev, g, cams, held, held_orig, bg, images, s))
        except Exception as err:  # e.g. out of memory at a large K: record it, go on with the next setting
            print(f"setting {s['text']!r} failed: {err!r}", flush=True)
            res["sweep"].append(dict(setting=s["text"], error=repr(err)))
            if dev.type == "cuda":
                torch.cuda.empty_cache()
        res["elapsed_s"] = time.perf_counter() - t_start
        _write(args, dev, res)
    if args.baseline:
        res["baseline"] = bench_baseline(args, dev, g, cams, held, held_orig, bg, images)
        print(json.dumps({"baseline": {x: y for x, y in res["baseline"].items() if x != "rows"}}), flush=True)
    res["elapsed_s"] = time.perf_counter() - t_start
    _write(args, dev, res)
    return 0


def _machine(dev: torch.device) -> dict:
    import gsw

    return dict(device=str(dev), gpu=torch.cuda.get_device_name(dev) if dev.type == "cuda" else None,
                cpu=platform.processor(), threads=torch.get_num_threads(), torch=torch.__version__,
                python=platform.python_version(), gsw=gsw.__version__, date=time.strftime("%Y-%m-%d %H:%M:%S"))


def _write(args, dev, res) -> None:
    tag = args.tag or f"fingerprint_{args.scene}_{dev.type}"
    out = Path(args.out) if args.out else ROOT / "benchmarks" / "results"
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{tag}.json.tmp"
    tmp.write_text(json.dumps(res, indent=1) + "\n")
    tmp.replace(out / f"{tag}.json")


if __name__ == "__main__":
    sys.exit(main())
