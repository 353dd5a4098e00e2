"""Pre-train, whiten and evaluate the HiDDeN watermark decoders, all bit lengths in one process.

1. ``gsw.decoder.pretrain.training.train_multi``: one encoder/decoder pair per bit length (``--bits``), all fed
   the same batches of random crops (+ flips) of the training photos, which stay on the device; device-only
   attacks (kornia's differentiable JPEG); curriculum: no attacks and a strong watermark (``--psnr-start``)
   for the first ``--clean-frac`` of the run, then the attacks ramp in and the PSNR tightens to ``--psnr``.
   Budgeted by wall time (``--train-s``).
2. Whitening of each decoder on unmarked photos (the training photos, mirrored, + random crops); ZCA with
   median centring by default (``--whiten-mode``, ``--whiten-center``).
3. Evaluation on ``--val`` photos at full size (real JPEG): encoder + raw decoder under every training
   noise layer and the paper's attacks; unbiasedness and false positives of the whitened and raw
   decoders (val photos x 1,000 messages); then the encoders alone are fine-tuned for ``--ft-s`` against
   the frozen whitened decoders (what ships) and evaluated again.
4. ``k{k}.pt`` (encoder, decoder, whitening) and ``k{k}.json`` (config, logs, results) in ``--out``,
   written as soon as each stage ends; ``--deadline-s`` shortens the later stages to end in time;
   ``--half`` rounds every encoder to float16 before it is evaluated and keeps only the last one in
   ``k{k}.pt`` (small enough to fetch from the GPU machine and to ``--init`` the next run from).
5. ``--refine-steps N``: the last encoders' residuals refined by N Adam steps against the frozen decoder
   (``gsw.mark.refine.refine_residual``; ``--refine-eot``: also through the training noise layers) and
   evaluated like the pairs; with ``--ft-s 0 --init-encoder encoder_ft`` it refines an earlier fine-tune.

``--init DIR`` continues from the ``k{k}.pt`` of an earlier run (its encoder and decoder; a warm restart with
a new optimizer and learning-rate schedule, so pass ``--clean-frac 0 --psnr-start`` = ``--psnr`` to skip the
curriculum).  ``benchmarks/export_decoders.py`` then writes the package weights, the manifest and the report.
Runs without the compiled extension: ``gsw/watermark`` is imported as a top-level package.

    python benchmarks/train_decoder.py --bits 32 48 64 --train-s 330 --ft-s 25 --out out/decoders
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "gsw"))  # import gsw/watermark without gsw/__init__ (no extension needed)

import torch  # noqa: E402

import watermark.training as T  # noqa: E402
from watermark.dwt import ll_subband  # noqa: E402
from watermark.evaluation import eval_attacks, unbiasedness  # noqa: E402
from watermark.hidden import bit_accuracy  # noqa: E402
from watermark.noise import paper_attacks, training_noise_layers  # noqa: E402
from watermark.refine import attack_cycle, refine_residual  # noqa: E402
from watermark.whitening import WhiteningLayer  # noqa: E402
from watermark.zoo import load_decoder  # noqa: E402

T0 = time.perf_counter()


def default_data() -> Path:
    for p in (ROOT / ".devdata" / "bsds500", ROOT.parent / "shared" / "data" / "bsds500"):
        if p.exists():
            return p
    return ROOT.parent / "shared" / "data" / "bsds500"


def left(args) -> float:
    return args.deadline_s - (time.perf_counter() - T0)


def log(msg: str) -> None:
    print(f"[{time.perf_counter() - T0:6.1f}s] {msg}", flush=True)


def make_val_fn(val_bank, cfg):
    gen = torch.Generator(device=val_bank.device).manual_seed(123)
    crops = T.bank_crops(val_bank, 64, cfg.crop, gen)
    msgs = {k: torch.randint(0, 2, (64, k), device=val_bank.device, generator=gen).float() for k in cfg.bits}

    @torch.no_grad()
    def val_fn(encs, decs, psnr):
        att = T.GpuAttacks(val_bank.device, 7)
        out = {}
        for e, d, k in zip(encs, decs, cfg.bits):
            x_w = T.embed_scaled(e, crops, msgs[k], psnr, cfg.enc_down)
            out[f"k{k}"] = {n: round(float(bit_accuracy(d(ll_subband(att.apply(n, x_w, 1.0).float())).float(),
                                                        msgs[k]).mean()), 4) for n in cfg.noise_layers}
            out[f"k{k}"]["view"] = round(float(bit_accuracy(d(ll_subband(att.view(x_w, 1.0))).float(),
                                                            msgs[k]).mean()), 4)
        return out

    return val_fn


def eval_chunked(args, emb, dec, images, attacks, k, seed, device, frac_of_left=1.0):
    """eval_attacks over chunks of 10 photos, stopping early when the time share runs out."""
    t_end = time.perf_counter() + max(0.0, left(args)) * frac_of_left
    parts = []
    for i in range(0, len(images), 10):
        if parts and time.perf_counter() > t_end:
            break
        parts.append(eval_attacks(emb, dec, images[i : i + 10], attacks, k, args.msgs_per_image,
                                  seed=seed + i, device=device))
    n = sum(p["n"] for p in parts)
    acc = {a: sum(p["bit_acc"][a] * p["n"] for p in parts) / n for a in attacks}
    var = {a: sum(p["n"] * (p["bit_acc_std"][a] ** 2 + (p["bit_acc"][a] - acc[a]) ** 2) for p in parts) / n
           for a in attacks}
    return {"bit_acc": acc, "bit_acc_std": {a: math.sqrt(v) for a, v in var.items()},
            "psnr": sum(p["psnr"] * p["n"] for p in parts) / n, "n": n, "num_images": n // args.msgs_per_image}


def load_init(run: Path, cfg: T.MultiConfig, encoder_key: str = "encoder") -> tuple[list, list]:
    """Encoders and decoders of an earlier run (``k{k}.pt`` per bit length), built for ``cfg``.

    ``encoder_key="encoder_ft"`` takes the run's fine-tuned encoder; a template encoder may grow on the way
    (:meth:`TemplateEncoder.load_grown_state_dict`: larger templates, a new or wider ``mlp`` branch)."""
    encs, decs = [], []
    for k in cfg.bits:
        blob = torch.load(run / f"k{k}.pt", map_location="cpu", weights_only=False)
        if encoder_key not in blob:
            raise SystemExit(f"--init {run}: k{k}.pt has no {encoder_key!r} (a --half checkpoint keeps only its "
                             f"last encoder: {[n for n in ('encoder', 'encoder_ft') if n in blob]})")
        enc = T.make_encoder(k, cfg)
        dec = T.HiddenDecoder(k, cfg.dec_blocks, cfg.channels, cfg.dec_norm)
        try:
            if isinstance(enc, T.TemplateEncoder):
                enc.load_grown_state_dict(blob[encoder_key])
            else:
                enc.load_state_dict(blob[encoder_key])
        except (RuntimeError, ValueError) as e:
            raise SystemExit(f"--init {run}: the {k}-bit encoder does not fit this configuration: {e}") from e
        dec.load_state_dict(blob["decoder"])
        encs.append(enc)
        decs.append(dec)
    return encs, decs


def refined_embedder(args, encoder, decoder, whitening, cfg, steps: int, device):
    """(imgs, msgs) -> watermarked imgs: the encoder's residual refined against the decoder (+ whitening)."""
    attack = (attack_cycle(T.GpuAttacks(device, 11).apply, cfg.noise_layers, args.refine_eot_every)
              if args.refine_eot else None)

    def embed(x, m):
        return refine_residual(lambda ll: whitening(decoder(ll).float()), x,
                               T.encoder_residual(encoder, x, m, cfg.enc_down), m, cfg.psnr_target, steps,
                               args.refine_lr, args.refine_margin, attack,
                               amp=device.type == "cuda" and not args.refine_fp32, schedule=args.refine_schedule)

    return embed


def encoder_state(encoder: torch.nn.Module, half: bool) -> dict[str, torch.Tensor]:
    """The encoder's state dict, floating tensors in float16 when ``half`` (on the CPU)."""
    return {n: (v.half() if half and v.is_floating_point() else v).cpu() for n, v in encoder.state_dict().items()}


def to_half(encoder: torch.nn.Module) -> None:
    """Round the encoder's weights to float16 in place (they stay float32 tensors)."""
    encoder.load_state_dict(encoder_state(encoder, True))


def shipped_whitening(decoder: torch.nn.Module, k: int) -> torch.nn.Module:
    """The package's whitening for ``k`` bits, after checking that ``decoder`` is the shipped decoder."""
    shipped = load_decoder(k)
    ours = {n: v.detach().cpu() for n, v in decoder.state_dict().items()}
    if any(not torch.equal(ours[n], v) for n, v in shipped.decoder.state_dict().items()):
        raise SystemExit(f"--shipped-whitening: the {k}-bit decoder is not the shipped one")
    return shipped.whitening


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bits", type=int, nargs="+", default=[32, 48, 64])
    ap.add_argument("--data", default=str(default_data()))
    ap.add_argument("--out", default=str(ROOT / "out" / "decoders"))
    ap.add_argument("--train-s", type=float, default=330.0, help="training wall-time budget (all bit lengths)")
    ap.add_argument("--steps", type=int, default=1000, help="step budget when --train-s 0")
    ap.add_argument("--ft-s", type=float, default=25.0, help="encoder fine-tune against the whitened decoders")
    ap.add_argument("--ft-lr", type=float, default=5e-4, help="learning rate of that fine-tune (cosine)")
    ap.add_argument("--ft-warp", default="same", choices=["same", "on", "off"],
                    help="view warp in the encoder fine-tune (same: as in training; off: the image-only task of "
                         "the pair's evaluation)")
    ap.add_argument("--ft-target", default="whitened", choices=["whitened", "raw"],
                    help="decoder output the encoder is fine-tuned against (and then evaluated with)")
    ap.add_argument("--shipped-whitening", action="store_true",
                    help="use the package's whitening (gsw/watermark/weights) instead of fitting one; the "
                         "decoders must be the shipped ones (checked)")
    ap.add_argument("--deadline-s", type=float, default=1e9, help="end everything by then (from the start)")
    ap.add_argument("--batch", type=int, default=64, help="per bit length")
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--psnr", type=float, default=30.0)
    ap.add_argument("--psnr-start", type=float, default=22.0)
    ap.add_argument("--clean-frac", type=float, default=0.3)
    ap.add_argument("--noise-ramp-end", type=float, default=0.6, help="attack strength reaches 1 at this fraction")
    ap.add_argument("--enc-down", type=int, default=2, help="encoder resolution divisor (training aid)")
    ap.add_argument("--channels", type=int, default=64)
    ap.add_argument("--dec-norm", default="standardize", choices=["none", "center", "standardize"],
                    help="decoder input normalisation (HiddenDecoder input_norm)")
    ap.add_argument("--templates", type=int, default=0, help="> 0: on/off template encoder aid of this side")
    ap.add_argument("--template-mlp", type=int, default=0,
                    help="> 0: nonlinear message -> template branch of this width (added at zero to an --init)")
    ap.add_argument("--template-refine", type=int, default=0,
                    help="> 0: image-adaptive conv refiner of the template of this width (added at zero to an --init)")
    ap.add_argument("--clean-chunk", action="store_true",
                    help="in the joint training half of every batch is never attacked (it still sees the view warp)")
    ap.add_argument("--ft-clean-chunk", action="store_true",
                    help="in the encoder fine-tune half of every batch is never attacked (clean accuracy weighs more)")
    ap.add_argument("--half", action="store_true",
                    help="round every encoder to float16 before its evaluation; k{k}.pt then keeps the decoder and "
                         "whitening (float32) and only the last encoder (fine-tuned if any) in float16")
    ap.add_argument("--skip-init-eval", action="store_true",
                    help="skip the evaluation before the fine-tune (pair, unbiasedness): for chained fine-tunes")
    ap.add_argument("--refine-steps", type=int, nargs="*", default=[],
                    help="also evaluate the fine-tuned pair with the encoder's residual refined for this many Adam "
                         "steps against the decoder (gsw.mark.refine.refine_residual); one evaluation each")
    ap.add_argument("--refine-lr", type=float, default=0.3, help="learning rate of that refinement")
    ap.add_argument("--refine-schedule", default="cosine", choices=["cosine", "constant"],
                    help="learning-rate schedule of that refinement")
    ap.add_argument("--refine-margin", type=float, default=0.0, help="logit margin of that refinement")
    ap.add_argument("--refine-eot", action="store_true",
                    help="refine on the clean images and through the training noise layers (one per step, in "
                         "turn; differentiable JPEG)")
    ap.add_argument("--refine-eot-every", type=int, default=1,
                    help="with --refine-eot, go through an attack on every n-th step only (the others are clean)")
    ap.add_argument("--refine-fp32", action="store_true",
                    help="refine with the decoder in float32 (default on CUDA: bf16 autocast, about twice as fast)")
    ap.add_argument("--view-warp", action="store_true",
                    help="every training sample also goes through a random view warp (rotation, zoom, foreshortening)")
    ap.add_argument("--balance", type=float, default=0.0,
                    help="weight of the unmarked-balance loss (decoder unbiased per bit on unmarked crops)")
    ap.add_argument("--balance-batch", type=int, default=16, help="unmarked crops per step for that loss")
    ap.add_argument("--freeze-bn", action="store_true",
                    help="decoder BatchNorm in eval mode (fine-tuning: train exactly the inference network)")
    ap.add_argument("--init", default=None, help="continue from DIR/k{bits}.pt of an earlier run "
                                                  "(with --train-s 0 --steps 0: no further training)")
    ap.add_argument("--init-encoder", default="encoder", choices=["encoder", "encoder_ft"],
                    help="which encoder of --init to start from (encoder_ft: its fine-tuned one, to chain fine-tunes)")
    ap.add_argument("--whiten-mode", default="zca", choices=["pca", "zca"])
    ap.add_argument("--whiten-center", default="median", choices=["mean", "median"])
    ap.add_argument("--whiten-eps", type=float, default=T.WHITEN_EIG_FLOOR, help="eigenvalue floor relative to the largest")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--log-every", type=int, default=200)
    ap.add_argument("--val-every-s", type=float, default=60.0)
    ap.add_argument("--whiten-crops", type=int, default=4000)
    ap.add_argument("--eval-images", type=int, default=100)
    ap.add_argument("--msgs-per-image", type=int, default=4)
    ap.add_argument("--num-messages", type=int, default=1000)
    ap.add_argument("--limit-images", type=int, default=None)
    ap.add_argument("--device", default=None)
    ap.add_argument("--amp", default="auto", choices=["auto", "on", "off"], help="bf16 autocast (auto: on CUDA)")
    args = ap.parse_args()
    if args.refine_eot_every < 1:
        ap.error("--refine-eot-every must be >= 1")
    device = torch.device(args.device if args.device else ("cuda" if torch.cuda.is_available() else "cpu"))
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    train_images = T.load_images(Path(args.data) / "train", args.limit_images)
    val_images = T.load_images(Path(args.data) / "val", args.limit_images)
    bank, val_bank = T.image_bank(train_images, device), T.image_bank(val_images, device)
    log(f"{len(train_images)} train / {len(val_images)} val photos, bank {tuple(bank.shape)} on {device}")
    amp = (device.type == "cuda") if args.amp == "auto" else args.amp == "on"
    cfg = T.MultiConfig(bits=tuple(args.bits), channels=args.channels, crop=args.crop, batch_size=args.batch,
                        lr=args.lr, psnr_start=args.psnr_start, psnr_target=args.psnr, clean_frac=args.clean_frac,
                        noise_ramp_end=args.noise_ramp_end,
                        steps=args.steps, time_budget_s=args.train_s if args.train_s > 0 else None, amp=amp,
                        channels_last=device.type == "cuda", seed=args.seed, log_every=args.log_every,
                        enc_down=args.enc_down, dec_norm=args.dec_norm, templates=args.templates,
                        template_mlp=args.template_mlp, template_refine=args.template_refine,
                        view_warp=args.view_warp, balance=args.balance, balance_batch=args.balance_batch,
                        freeze_bn=args.freeze_bn, clean_chunk=args.clean_chunk)
    encs0, decs0 = load_init(Path(args.init), cfg, args.init_encoder) if args.init else (None, None)
    trained = not (args.init and args.train_s <= 0 and args.steps <= 0)
    if not trained:
        st = {"encoders": [e.to(device).eval() for e in encs0], "decoders": [d.to(device).eval() for d in decs0],
              "step": 0, "elapsed": 0.0, "log": [], "val": [], "steps_per_s": 0.0}
    else:
        st = T.train_multi(cfg, bank, encoders=encs0, decoders=decs0, val_fn=make_val_fn(val_bank, cfg),
                           val_every_s=args.val_every_s, tag="train ")
    prev = {k: json.loads((Path(args.init) / f"k{k}.json").read_text()) for k in cfg.bits} if args.init else {}
    if args.init:
        st["step"] += prev[cfg.bits[0]]["steps"]
        st["elapsed"] += prev[cfg.bits[0]]["train_elapsed_s"]
    encs, decs = st["encoders"], st["decoders"]
    if args.half:
        for e in encs:
            to_half(e)
    log(f"trained {st['step']} steps in {st['elapsed']:.0f} s ({st['steps_per_s']:.2f} steps/s)")
    torch.backends.cudnn.benchmark = False  # evaluation sees many image sizes
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False  # whitening in float32
    if args.shipped_whitening:
        whitens, nfit = [shipped_whitening(d, k) for d, k in zip(decs, cfg.bits)], 0
        log("whitening: the shipped one")
    else:
        whitens, nfit = T.fit_whitening_multi(decs, train_images, bank, num_crops=args.whiten_crops,
                                              mode=args.whiten_mode, center=args.whiten_center, eps=args.whiten_eps)
        log(f"whitening fitted on {nfit} samples")
    whitens = [w.to(device) for w in whitens]
    dev_name = torch.cuda.get_device_name(0) if device.type == "cuda" else (platform.processor() or "cpu")
    metas = {}
    for i, k in enumerate(cfg.bits):
        metas[k] = {
            "num_bits": k, "config": {**dataclasses.asdict(cfg), "num_bits": k, "ft_s": args.ft_s},
            "args": vars(args), "steps": st["step"], "train_elapsed_s": st["elapsed"],
            "steps_per_s": st["steps_per_s"], "device": dev_name, "torch": torch.__version__,
            "python": platform.python_version(), "num_train_images": len(train_images),
            "num_val_images": len(val_images), "whitening_fit_samples": nfit, "results": {},
            "train_log": st["log"], "val_log": st["val"], "ft_log": [],
        }

    def save(stage: str, ft_encs=None) -> None:
        for i, k in enumerate(cfg.bits):
            metas[k]["wall_s"] = time.perf_counter() - T0
            metas[k]["stage"] = stage
            blob = {"stage": stage, "num_bits": k, "decoder": decs[i].state_dict(),
                    "whitening": whitens[i].state_dict(), "config": metas[k]["config"], "step": st["step"]}
            if not (args.half and ft_encs is not None):
                blob["encoder"] = encoder_state(encs[i], args.half)
            if ft_encs is not None:
                blob["encoder_ft"] = encoder_state(ft_encs[i], args.half)
            torch.save(blob, out / f"k{k}.pt")
            (out / f"k{k}.json").write_text(json.dumps(metas[k], indent=1))

    save("whitened")
    attacks = dict(training_noise_layers("real"))  # evaluation uses the real codec only
    attacks.update(paper_attacks())
    val_eval = val_images[: args.eval_images]
    psnr_t = cfg.psnr_target
    if not args.skip_init_eval:  # a chained fine-tune: the --init run's numbers stand
        for i, k in enumerate(cfg.bits):
            emb = lambda x, m, e=encs[i]: T.embed_scaled(e, x, m, psnr_t, cfg.enc_down)  # noqa: E731
            r = eval_chunked(args, emb, decs[i], val_eval, attacks, k, 1, device,
                             frac_of_left=0.45 / (len(cfg.bits) - i))
            metas[k]["results"]["pair_raw"] = r
            log(f"k={k} pair_raw ({r['n']} pairs, PSNR {r['psnr']:.1f}): "
                + " ".join(f"{a}={v:.4f}" for a, v in r["bit_acc"].items()))
        save("evaluated_raw")
        for i, k in enumerate(cfg.bits):
            dw = lambda ll, d=decs[i], w=whitens[i]: w(d(ll).float())  # noqa: E731
            u = unbiasedness(dw, val_images, k, args.num_messages, seed=2, device=device, extra_views=10)
            metas[k]["results"]["unbiased_whitened"] = u
            metas[k]["results"]["unbiased_raw"] = unbiasedness(decs[i], val_images, k, args.num_messages, seed=2,
                                                               device=device)
            emb = lambda x, m, e=encs[i]: T.embed_scaled(e, x, m, psnr_t, cfg.enc_down)  # noqa: E731
            metas[k]["results"]["pair_whitened_before_ft"] = eval_chunked(
                args, emb, dw, val_eval, {"identity": attacks["identity"]}, k, 1, device, frac_of_left=0.05)
            log(f"k={k} unbiased: acc={u['mean_bit_acc']:.4f} p1dev={u['per_bit_p1_max_dev']:.3f} "
                f"views_p1dev={u.get('views_per_bit_p1_max_dev'):.3f} fp={u['false_positives']} "
                f"max={u['max_matching_bits']} before-ft whitened acc="
                f"{metas[k]['results']['pair_whitened_before_ft']['bit_acc']['identity']:.4f}")
        save("evaluated_unbiased")
    ft_s = min(args.ft_s, max(0.0, left(args) * 0.4))
    targets = whitens if args.ft_target == "whitened" else [WhiteningLayer(k).to(device) for k in cfg.bits]
    final, ft_encs = encs, None  # the encoders evaluated last (and refined)
    if ft_s >= 3:
        ft_encs = [copy.deepcopy(e) for e in encs]
        warp = cfg.view_warp if args.ft_warp == "same" else args.ft_warp == "on"
        fcfg = dataclasses.replace(cfg, time_budget_s=ft_s, lr=args.ft_lr, view_warp=warp,
                                   clean_chunk=args.ft_clean_chunk, log_every=max(10, args.log_every // 4))
        torch.backends.cudnn.benchmark = device.type == "cuda"
        ft = T.train_multi(fcfg, bank, encoders=ft_encs, decoders=decs, whitenings=targets,
                           finetune_encoders=True, tag="ft ")
        torch.backends.cudnn.benchmark = False
        final = ft_encs = ft["encoders"]
        log(f"encoder fine-tune: {ft['step']} steps in {ft['elapsed']:.0f} s")
        if args.half:  # what is evaluated below is exactly what k{k}.pt holds
            for e in ft_encs:
                to_half(e)
        for i, k in enumerate(cfg.bits):
            metas[k]["ft_log"] = ft["log"]
            metas[k]["ft_steps"] = ft["step"]
            metas[k]["config"]["ft_s"] = round(ft["elapsed"], 1)
            metas[k]["config"].update(ft_lr=args.ft_lr, ft_view_warp=warp, ft_target=args.ft_target,
                                      ft_clean_chunk=args.ft_clean_chunk)
            if args.init_encoder == "encoder_ft" and not trained:  # chained fine-tunes: count the earlier ones too
                before = prev[k]
                metas[k]["ft_steps_total"] = ft["step"] + before.get("ft_steps_total", before.get("ft_steps", 0))
                metas[k]["ft_s_total"] = round(ft["elapsed"] + before.get(
                    "ft_s_total", before["config"].get("ft_s", 0) if "ft_steps" in before else 0), 1)
        save("finetuned", ft_encs)
        for i, k in enumerate(cfg.bits):
            emb = lambda x, m, e=ft_encs[i]: T.embed_scaled(e, x, m, psnr_t, cfg.enc_down)  # noqa: E731
            dw = lambda ll, d=decs[i], w=targets[i]: w(d(ll).float())  # noqa: E731
            r = eval_chunked(args, emb, dw, val_eval, attacks, k, 1, device,
                             frac_of_left=0.8 / (len(cfg.bits) - i))
            metas[k]["results"][f"pair_{args.ft_target}_ft"] = r
            log(f"k={k} pair_{args.ft_target}_ft ({r['n']} pairs): "
                + " ".join(f"{a}={v:.4f}" for a, v in r["bit_acc"].items()))
    tuned = ft_encs is not None or (args.init_encoder == "encoder_ft" and not trained)
    if ft_encs is None and tuned:  # no new fine-tune of the init's fine-tuned encoder: its counts stand
        for k in cfg.bits:
            metas[k].update({n: prev[k][n] for n in ("ft_steps", "ft_steps_total", "ft_s_total") if n in prev[k]})
    for steps in args.refine_steps:
        for i, k in enumerate(cfg.bits):
            r = eval_chunked(args, refined_embedder(args, final[i], decs[i], targets[i], cfg, steps, device),
                             lambda ll, d=decs[i], w=targets[i]: w(d(ll).float()), val_eval, attacks, k, 1, device,
                             frac_of_left=0.8 / (len(cfg.bits) - i))
            r["refine"] = {"steps": steps, "lr": args.refine_lr, "margin": args.refine_margin, "eot": args.refine_eot,
                           "eot_every": args.refine_eot_every, "schedule": args.refine_schedule,
                           "bf16": device.type == "cuda" and not args.refine_fp32}
            name = f"pair_{args.ft_target}{'_ft' if tuned else ''}_refine{steps}"
            metas[k]["results"][name] = r
            log(f"k={k} {name} ({r['n']} pairs, PSNR {r['psnr']:.1f}): "
                + " ".join(f"{a}={v:.4f}" for a, v in r["bit_acc"].items()))
        save("refined", ft_encs)
    save("done", ft_encs)
    log("done")


if __name__ == "__main__":
    main()
