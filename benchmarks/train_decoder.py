"""Pre-train, whiten, evaluate the HiDDeN watermark decoders (one process per bit length).

Per bit length k (``--bits 32 48 64``; with several, one subprocess each, concurrently on one GPU):

1. train encoder + decoder on random 128x128 crops + flips of ``--train`` (time budget ``--train-s``),
   logging bit accuracy per noise layer and validating on ``--val``; checkpoint ``k{k}.pt`` in ``--out``
   every minute (rerun the same command to resume);
2. PCA-whiten the decoder on unmarked training photos;
3. fine-tune the encoder alone against the frozen whitened decoder (``--ft-s``);
4. evaluate on ``--val`` (full-size photos): bit accuracy clean / under each training noise layer /
   under the paper's fixed attacks, for the pre-trained pair and for the shipped (whitened) decoder;
   unbiasedness and false positives of the whitened decoder on unmarked photos x 1,000 messages;
5. write ``k{k}.pt`` (final state, whitening included) and ``k{k}.json`` (config, logs, results).

``benchmarks/export_decoders.py`` then writes the package weights, the manifest and the report.

Runs without the compiled extension: ``gsw/watermark`` is imported as a top-level package.

    python benchmarks/train_decoder.py --bits 32 48 64 --train-s 300 --ft-s 60 --out out/decoders
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "gsw"))  # import gsw/watermark without gsw/__init__ (no extension needed)

import torch  # noqa: E402

import watermark.training as T  # noqa: E402
from watermark.evaluation import eval_attacks, unbiasedness  # noqa: E402
from watermark.hidden import bit_accuracy  # noqa: E402
from watermark.dwt import ll_subband  # noqa: E402
from watermark.noise import paper_attacks, training_noise_layers  # noqa: E402


def default_data() -> Path:
    for p in (ROOT / ".devdata" / "bsds500", ROOT.parent / "shared" / "data" / "bsds500"):
        if p.exists():
            return p
    return ROOT.parent / "shared" / "data" / "bsds500"


def make_val_fn(val_images, cfg, device):
    gen = torch.Generator().manual_seed(123)
    crops = T.random_crops(val_images, 64, 256, gen, device)
    msgs = torch.randint(0, 2, (64, cfg.num_bits), generator=gen).float().to(device)
    layers = training_noise_layers(cfg.jpeg_mode)

    @torch.no_grad()
    def val_fn(enc, dec, psnr):
        g = torch.Generator().manual_seed(7)
        x_w = T.embed(enc, crops, msgs, psnr)
        out = {}
        for name, layer in layers.items():
            layer.strength = 1.0
            out[name] = round(float(bit_accuracy(dec(ll_subband(layer(x_w, generator=g))).float(), msgs).mean()), 4)
        return out

    return val_fn


def run_one(args, k: int) -> None:
    device = torch.device(args.device if args.device else ("cuda" if torch.cuda.is_available() else "cpu"))
    torch.set_num_threads(args.threads)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / f"k{k}.pt"
    t0 = time.perf_counter()
    train_images = T.load_images(Path(args.data) / "train", args.limit_images)
    val_images = T.load_images(Path(args.data) / "val", args.limit_images)
    cfg = T.TrainConfig(num_bits=k, batch_size=args.batch, crop=args.crop, lr=args.lr,
                        psnr_start=args.psnr_start, psnr_target=args.psnr, time_budget_s=args.train_s,
                        steps=args.steps, jpeg_mode=args.jpeg_mode,
                        amp=(device.type == "cuda") if args.amp == "auto" else args.amp == "on", seed=args.seed + k, log_every=args.log_every)
    if args.train_s is None:
        cfg.time_budget_s = None
    prev = torch.load(ckpt, map_location="cpu", weights_only=False) if ckpt.exists() else None
    if prev is not None and prev.get("stage") == "done":
        print(f"[k={k}] already done", flush=True)
        return
    state = T.train(cfg, train_images, device, ckpt_path=ckpt, val_fn=make_val_fn(val_images, cfg, device),
                    val_every_s=args.val_every_s)
    enc, dec = state.pop("modules")
    t_train = time.perf_counter() - t0
    whiten, raw = T.fit_decoder_whitening(dec, train_images, device, num_crops=args.whiten_crops)
    whiten = whiten.to(device)
    # pre-trained pair, before the encoder fine-tune
    dec_raw = lambda ll: dec(ll)  # noqa: E731
    dec_white = lambda ll: whiten(dec(ll).float())  # noqa: E731
    attacks = dict(training_noise_layers("real"))  # evaluation uses the real codec only
    attacks.update(paper_attacks())
    emb = lambda x, m: T.embed(enc, x, m, cfg.psnr_target)  # noqa: E731
    val_eval = val_images[: args.eval_images]
    res: dict = {}
    dec.eval()
    res["pair_raw"] = eval_attacks(emb, dec_raw, val_eval, attacks, k, args.msgs_per_image, seed=1, device=device)
    res["pair_whitened_before_ft"] = eval_attacks(emb, dec_white, val_eval, {"identity": attacks["identity"]}, k,
                                                  args.msgs_per_image, seed=1, device=device)
    ft_log = []
    if args.ft_s > 0:
        ft_log = T.finetune_encoder(enc, dec, whiten, cfg, train_images, device, time_budget_s=args.ft_s)
        res["pair_whitened"] = eval_attacks(emb, dec_white, val_eval, attacks, k, args.msgs_per_image, seed=1,
                                            device=device)
    res["unbiased_whitened"] = unbiasedness(dec_white, val_images, k, 1000, seed=2, device=device, extra_views=10)
    res["unbiased_raw"] = unbiasedness(dec_raw, val_images, k, 1000, seed=2, device=device)
    meta = {
        "num_bits": k,
        "config": dataclasses.asdict(cfg),
        "args": vars(args),
        "steps": state["step"],
        "train_elapsed_s": state["elapsed"],
        "wall_s": time.perf_counter() - t0,
        "wall_train_s": t_train,
        "device": torch.cuda.get_device_name(0) if device.type == "cuda" else platform.processor() or "cpu",
        "torch": torch.__version__,
        "python": platform.python_version(),
        "num_train_images": len(train_images),
        "num_val_images": len(val_images),
        "whitening_fit_samples": int(raw.shape[0]),
        "results": res,
        "train_log": state["log"],
        "val_log": state["val"],
        "ft_log": ft_log,
    }
    state.update(stage="done", encoder=enc.state_dict(), decoder=dec.state_dict(),
                 whitening=whiten.cpu().state_dict(), meta=meta)
    state.pop("optimizer", None)
    T._atomic_save(state, ckpt)
    (out / f"k{k}.json").write_text(json.dumps(meta, indent=1))
    brief = {n: round(v, 4) for n, v in res["pair_raw"]["bit_acc"].items()}
    print(f"[k={k}] DONE steps={state['step']} pair_raw={brief}", flush=True)
    if "pair_whitened" in res:
        print(f"[k={k}] pair_whitened={ {n: round(v, 4) for n, v in res['pair_whitened']['bit_acc'].items()} }")
    u = res["unbiased_whitened"]
    print(f"[k={k}] unbiased: acc={u['mean_bit_acc']:.4f} p1dev={u['per_bit_p1_max_dev']:.3f} "
          f"views_p1dev={u.get('views_per_bit_p1_max_dev')} fp={u['false_positives']} max={u['max_matching_bits']}",
          flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bits", type=int, nargs="+", default=[32, 48, 64])
    ap.add_argument("--data", default=str(default_data()))
    ap.add_argument("--out", default=str(ROOT / "out" / "decoders"))
    ap.add_argument("--train-s", type=float, default=300.0, help="training time budget per bit length")
    ap.add_argument("--steps", type=int, default=1000, help="step budget when --train-s 0")
    ap.add_argument("--ft-s", type=float, default=60.0, help="encoder fine-tune against the whitened decoder")
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--psnr", type=float, default=30.0)
    ap.add_argument("--psnr-start", type=float, default=24.0)
    ap.add_argument("--jpeg-mode", default="real_diffgrad", choices=["real", "diff", "real_diffgrad"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--log-every", type=int, default=100)
    ap.add_argument("--val-every-s", type=float, default=90.0)
    ap.add_argument("--whiten-crops", type=int, default=4000)
    ap.add_argument("--eval-images", type=int, default=100)
    ap.add_argument("--msgs-per-image", type=int, default=4)
    ap.add_argument("--limit-images", type=int, default=None)
    ap.add_argument("--threads", type=int, default=4)
    ap.add_argument("--device", default=None)
    ap.add_argument("--amp", default="auto", choices=["auto", "on", "off"], help="bf16 autocast (auto: on CUDA)")
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.train_s is not None and args.train_s <= 0:
        args.train_s = None
    if len(args.bits) == 1 or args.one:
        for k in args.bits:
            run_one(args, k)
        return
    procs = []
    for k in args.bits:
        cmd = [sys.executable, "-u", __file__, "--one", *sys.argv[1:]]
        i = cmd.index("--bits")
        j = i + 1
        while j < len(cmd) and not cmd[j].startswith("--"):
            j += 1
        cmd[i:j] = ["--bits", str(k)]
        procs.append(subprocess.Popen(cmd, env=dict(os.environ, PYTHONUNBUFFERED="1")))
    rcs = [p.wait() for p in procs]
    print("return codes", dict(zip(args.bits, rcs)), flush=True)
    sys.exit(max(rcs))


if __name__ == "__main__":
    main()
