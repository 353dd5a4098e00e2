"""Export trained decoders into the package and write the report.

Reads ``k{bits}.pt`` / ``k{bits}.json`` written by ``benchmarks/train_decoder.py``, writes
``gsw/watermark/weights/hidden_k{bits}.pt`` (decoder + whitening, float32) and ``manifest.json``
(sha256, size, provenance), re-checks the exported files through ``load_decoder`` on the CPU (unbiasedness
on the val photos), measures kornia's differentiable JPEG against the real codec, and writes
``benchmarks/results/decoder.{json,md}``.

    python benchmarks/export_decoders.py --run-dir /path/with/k32.pt --data ../shared/data/bsds500

``--report-only`` leaves the shipped weights alone: it re-measures their unbiasedness on the CPU, merges the
encoder fine-tunes of ``--ft-runs`` (``train_decoder.py --train-s 0 --steps 0 --init ...``) and rewrites the
report from ``benchmarks/results/decoder.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "gsw"))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from watermark import noise as N  # noqa: E402
from gsw.metrics.image import psnr  # noqa: E402
from watermark.evaluation import bootstrap_ci95, eval_attacks, unbiasedness  # noqa: E402
from watermark.hidden import HiddenDecoder  # noqa: E402
from watermark.training import (WHITEN_EIG_FLOOR, embed_scaled, fit_whitening_multi, image_bank,  # noqa: E402
                                load_images, load_run_encoder)
from watermark.whitening import WhiteningLayer  # noqa: E402
from watermark.zoo import WEIGHTS_DIR, load_decoder, record_in_manifest, save_decoder  # noqa: E402


def jpeg_fidelity(images: list[torch.Tensor], qualities=(90, 70, 50, 30)) -> dict:
    """PSNR (dB) real JPEG vs original, kornia diff JPEG vs original, diff vs real, on 256x256 crops."""
    x = torch.stack([img[:, :256, :256] for img in images if min(img.shape[-2:]) >= 256]).float() / 255
    ps = lambda a, b: float(psnr(a.flatten(0, 1), b.flatten(0, 1)))  # noqa: E731  (one MSE over all images)
    out = {}
    for q in qualities:
        qt = torch.full((x.shape[0],), float(q))
        r, d = N.real_jpeg(x, qt), N.diff_jpeg(x, qt)
        out[str(q)] = {"real_vs_orig": ps(r, x), "diff_vs_orig": ps(d, x), "diff_vs_real": ps(d, r)}
    return {"num_images": int(x.shape[0]), "psnr_db": out}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--run-dir", help="the training run to export (not with --report-only)")
    ap.add_argument("--report-only", action="store_true", help="keep the shipped weights; refresh the report")
    ap.add_argument("--ft-runs", nargs="*", default=[],
                    help="runs of encoder-only fine-tunes of the shipped decoders, merged into the report")
    ap.add_argument("--recheck-bits", type=int, nargs="*", default=[],
                    help="re-measure a fine-tuned pair on the CPU for these bit lengths: its encoder with the "
                         "shipped decoder (package loader), new messages, 95 %% photo-bootstrap interval")
    ap.add_argument("--recheck-run", default=None,
                    help="the run whose encoder_ft is re-checked (default: the last of --ft-runs)")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "bsds500"))
    ap.add_argument("--bits", type=int, nargs="+", default=[32, 48, 64])
    ap.add_argument("--results", default=str(ROOT / "benchmarks" / "results" / "decoder"))
    ap.add_argument("--refit-whitening", action="store_true",
                    help="refit the whitening here on the CPU (float32) and re-measure unbiasedness with it")
    ap.add_argument("--whiten-crops", type=int, default=1600)
    ap.add_argument("--whiten-eps", type=float, default=WHITEN_EIG_FLOOR)
    args = ap.parse_args()
    if args.recheck_bits and not (args.recheck_run or args.ft_runs):
        ap.error("--recheck-bits needs --recheck-run or --ft-runs")
    if args.report_only:
        return refresh_report(args)
    if not args.run_dir:
        ap.error("--run-dir is required (or --report-only)")
    run = Path(args.run_dir)
    val_images = load_images(Path(args.data) / "val")
    train_images = load_images(Path(args.data) / "train") if args.refit_whitening else []
    out = Path(args.results)
    report = {"runs": {}, "cpu_recheck": {}}
    if out.with_suffix(".json").exists():  # the bit lengths not exported now keep their report entries
        old = json.loads(out.with_suffix(".json").read_text())
        report = {key: {b: v for b, v in old.get(key, {}).items() if int(b) not in args.bits} for key in report}
    for k in args.bits:
        state = torch.load(run / f"k{k}.pt", map_location="cpu", weights_only=False)
        meta = json.loads((run / f"k{k}.json").read_text())
        cfg = meta["config"]  # the architecture the decoder was trained with (input_norm included)
        dec = HiddenDecoder(k, cfg.get("dec_blocks", 8), cfg.get("channels", 64), cfg.get("dec_norm", "none"))
        dec.load_state_dict(state["decoder"])
        dec.eval()
        wl = WhiteningLayer(k)
        wl.load_state_dict(state["whitening"])
        if args.refit_whitening:
            with torch.no_grad():
                (wl,), nfit = fit_whitening_multi([dec], train_images, image_bank(train_images, "cpu"),
                                                  num_crops=args.whiten_crops, eps=args.whiten_eps)
                fn = lambda ll, d=dec, w=wl: w(d(ll))  # noqa: E731
                meta["results"]["unbiased_whitened"] = unbiasedness(fn, val_images, k, 1000, seed=2,
                                                                    extra_views=10,
                                                                    fit_images=len(train_images))
                meta["results"]["unbiased_raw"] = unbiasedness(dec, val_images, k, 1000, seed=2)
            meta["results"].pop("pair_whitened_before_ft", None)  # measured with the replaced whitening
            meta["whitening_refit"] = {"device": "cpu", "dtype": "float32", "samples": nfit, "eps": args.whiten_eps,
                                       "mode": "zca", "center": "median"}
            meta["whitening_fit_samples"] = nfit
        prov = {"steps": meta["steps"], "train_s": round(meta["train_elapsed_s"]), "device": meta["device"],
                "torch": meta["torch"], "data": "bsds500/train (200 photos), whitening on the same photos"}
        path = WEIGHTS_DIR / f"hidden_k{k}.pt"
        save_decoder(dec, wl, path, meta=prov)
        record_in_manifest(path, prov)  # the other bit lengths' entries stay
        keep = ("steps", "steps_per_s", "train_elapsed_s", "wall_s", "device", "torch", "python", "config", "args",
                "results", "whitening_fit_samples", "num_train_images", "val_log", "train_log", "whitening_refit")
        report["runs"][str(k)] = {x: meta[x] for x in keep if x in meta}
    for k in args.bits:  # the exported files, through the public loader, on the CPU
        model = load_decoder(k)
        with torch.no_grad():
            report["cpu_recheck"][str(k)] = unbiasedness(model, val_images, k, 1000, seed=2)
    report["jpeg_fidelity"] = jpeg_fidelity(val_images)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(report, indent=1))
    out.with_suffix(".md").write_text(markdown(report, sorted(int(b) for b in report["runs"])))
    print(out.with_suffix(".md").read_text())


def refresh_report(args) -> None:
    """Re-measure the shipped decoders' unbiasedness and merge encoder fine-tunes into the existing report."""
    out = Path(args.results)
    rep = json.loads(out.with_suffix(".json").read_text())
    val_images = load_images(Path(args.data) / "val")
    num_fit = len(list((Path(args.data) / "train").glob("*.jpg")))
    for k in args.bits:
        run = rep["runs"][str(k)]
        model = load_decoder(k)
        with torch.no_grad():
            u = unbiasedness(model, val_images, k, 1000, seed=2, extra_views=10, fit_images=num_fit)
        old = run["results"]["unbiased_whitened"]
        if (u["mean_bit_acc"], u["per_bit_p1_max_dev"]) != (old["mean_bit_acc"], old["per_bit_p1_max_dev"]):
            raise SystemExit(f"{k} bits: the shipped decoder no longer gives the reported statistics")
        run["results"]["unbiased_whitened"] = u
        for ft_dir in args.ft_runs:
            if not (Path(ft_dir) / f"k{k}.json").exists():
                continue
            meta = json.loads((Path(ft_dir) / f"k{k}.json").read_text())
            for name, r in meta["results"].items():
                if name.endswith("_ft") or "_ft_refine" in name:
                    run["results"][name] = {**r, "config": {c: meta["config"].get(c) for c in
                                                            ("ft_s", "ft_lr", "ft_view_warp", "ft_target",
                                                             "templates", "template_mlp", "ft_clean_chunk")},
                                            "ft_steps": meta.get("ft_steps_total", meta.get("ft_steps")),
                                            "ft_s_total": meta.get("ft_s_total", meta["config"].get("ft_s")),
                                            "device": meta["device"]}
    for k in args.recheck_bits:
        rep["runs"][str(k)]["results"]["pair_ft_cpu_recheck"] = cpu_pair_recheck(
            Path(args.recheck_run or args.ft_runs[-1]), k, val_images)
    out.with_suffix(".json").write_text(json.dumps(rep, indent=1))
    out.with_suffix(".md").write_text(markdown(rep, args.bits))
    print(out.with_suffix(".md").read_text())


@torch.no_grad()
def cpu_pair_recheck(run: Path, k: int, val_images: list[torch.Tensor], msgs_per_image: int = 4) -> dict:
    """The fine-tuned encoder of ``run`` with the shipped decoder (raw outputs, loaded and checksum-checked by
    ``load_decoder``) on every val photo, messages drawn anew (seed 1000 + photo index), every training noise
    layer with the real codec; clean accuracy with a 95 % bootstrap interval over photos."""
    meta = json.loads((run / f"k{k}.json").read_text())
    enc, cfg = load_run_encoder(run, k)
    dec = load_decoder(k).decoder
    attacks = dict(N.training_noise_layers("real"))
    per = {a: [] for a in attacks}
    for i, img in enumerate(val_images):
        r = eval_attacks(lambda x, m: embed_scaled(enc, x, m, cfg.psnr_target, cfg.enc_down), dec, [img],
                         attacks, k, msgs_per_image, seed=1000 + i)
        for a in attacks:
            per[a].append(r["bit_acc"][a])
    return {"bit_acc": {a: float(np.mean(v)) for a, v in per.items()}, "n": msgs_per_image * len(val_images),
            "identity_ci95": bootstrap_ci95(per["identity"]), "device": "cpu",
            "encoder": {"templates": cfg.templates, "template_mlp": cfg.template_mlp,
                        "ft_s_total": meta.get("ft_s_total", meta["config"].get("ft_s")),
                        "pair_on_gpu": meta["results"]["pair_raw_ft"]["bit_acc"]["identity"]}}


def _pct(v: float) -> str:
    return f"{100 * v:.1f}"


def markdown(rep: dict, bits: list[int]) -> str:
    r0 = rep["runs"][str(bits[0])]
    cfg = r0["config"]
    a0 = r0.get("args", {})
    wmode, wcenter = a0.get("whiten_mode", "pca").upper(), a0.get("whiten_center", "mean")
    cont = (f" The run continued an earlier one (`--init`: warm restart with a new optimizer and schedule, lr "
            f"{cfg['lr']}, no curriculum); steps and time are totals over the chain of runs." if a0.get("init") else "")
    lines = [
        f"## Watermark decoders (HiDDeN pre-training, {wmode} whitening)",
        "",
        f"Trained on {r0['device']} (torch {r0['torch']}, Python {r0['python']}), "
        + (f"the bit lengths {', '.join(map(str, bits))} together in one process (`train_multi`: one "
           "encoder/decoder pair each, same image batches, one fused AdamW step)"
           if len(a0.get("bits", bits)) > 1 else
           f"one `train_multi` process per bit length ({', '.join(map(str, bits))}) side by side on that GPU")
        + f", {r0['train_elapsed_s']:.0f} s of training, {r0['steps']} steps "
        f"({r0.get('steps_per_s', float('nan')):.1f} steps/s), batch {cfg['batch_size']} per bit length of random "
        f"{cfg['crop']}x{cfg['crop']} crops + flips of bsds500/train kept on the GPU, AdamW lr {cfg['lr']} "
        f"warmup + cosine, bf16 autocast, channels_last. Curriculum: the first {cfg.get('clean_frac', 0):.0%} of the "
        f"run without attacks at PSNR {cfg['psnr_start']:.0f} dB, then attack strength ramped to 1 by "
        f"{cfg.get('noise_ramp_end', 0):.0%} and PSNR to {cfg['psnr_target']:.0f} dB by {cfg.get('psnr_ramp_end', 0):.0%}; "
        f"{cfg.get('noise_chunks', 1)} random training attacks per batch (device-only, kornia differentiable JPEG); "
        f"encoder run at 1/{cfg.get('enc_down', 1)} resolution (training aid); on/off template encoder aid "
        f"of side {cfg.get('templates', 0)} (0 = off); view warp "
        + ("on (every sample also rotated by up to +-180 deg, zoomed x0.71-1.4 and foreshortened down to x0.5 "
           "along a random direction, ramped with the attack strength: what another viewpoint does to a "
           "surface texture)" if cfg.get("view_warp") else "off") + f".{cont} "
        + (f"Unmarked-balance loss (weight {cfg['balance']}, {cfg.get('balance_batch', 16)} unmarked crops of side "
           f"128-320 per step, decoded with eval-mode BatchNorm) on "
           + ", ".join(str(k) for k in bits if rep["runs"][str(k)]["config"].get("balance", 0) > 0)
           + " bits; " if any(rep["runs"][str(k)]["config"].get("balance", 0) > 0 for k in bits) else "")
        + ("BatchNorm frozen (eval mode) in the last run. " if cfg.get("freeze_bn") else "")
        + f"{wmode} whitening, {wcenter}-centred, fitted on the decoder outputs of the train photos, their "
        f"mirror images and {r0.get('whitening_fit_samples', 0) - 2 * r0.get('num_train_images', 200):,} random crops"
        + (f", on the CPU in float32 with eigenvalue floor {r0['whitening_refit']['eps']:g} x the largest "
           "(`export_decoders.py --refit-whitening`)" if r0.get("whitening_refit") else "") + ". "
        "All numbers below on bsds500/val (100 photos, full size, real JPEG); pair accuracies from the GPU run, "
        + ("unmarked statistics from the CPU refit; " if r0.get("whitening_refit") else "")
        + "`benchmarks/train_decoder.py`, `benchmarks/export_decoders.py`.",
        "",
        f"### Bit accuracy (%) of encoder + decoder, random messages on val photos "
        f"({r0['results']['pair_raw']['n']} pairs)",
        "",
        "Pre-trained pair (raw decoder): target >= 99.5 clean, >= 90 under each training noise layer.",
        "",
    ]
    names = list(rep["runs"][str(bits[0])]["results"]["pair_raw"]["bit_acc"].keys())
    lines.append("| attack | " + " | ".join(f"{k} bits" for k in bits) + " |")
    lines.append("|---|" + "---|" * len(bits))
    for n in names:
        lines.append(f"| {n} | " + " | ".join(_pct(rep["runs"][str(k)]["results"]["pair_raw"]["bit_acc"][n])
                                              for k in bits) + " |")
    lines.append("| PSNR of marked photos (dB) | " + " | ".join(
        f"{rep['runs'][str(k)]['results']['pair_raw']['psnr']:.1f}" for k in bits) + " |")
    res = {k: rep["runs"][str(k)]["results"] for k in bits}
    ft_names = [n for n in ("pair_whitened_ft", "pair_raw_ft") if any(n in res[k] for k in bits)]
    for fn in ft_names:
        f0 = next(res[k][fn] for k in bits if fn in res[k])
        c = f0["config"]
        what = "the shipped (whitened) decoder" if c["ft_target"] == "whitened" else "the raw decoder"
        arch = (f"on/off templates of side {c['templates']}"
                + (f" + a nonlinear message -> tile branch (MLP width {c['template_mlp']})" if c.get("template_mlp")
                   else "") if c.get("templates") else "HiDDeN encoder")
        lines += ["", f"Encoder ({arch}) fine-tuned against {what}, decoder frozen (on {f0['device']}, "
                      f"cosine lr, training noise layers, view warp {'on' if c['ft_view_warp'] else 'off'}: the "
                      f"image-only task this table measures; the decoder is the one that ships), {f0['n']} pairs, "
                      f"PSNR {f0['psnr']:.1f} dB:", "",
                  "| attack | " + " | ".join(f"{k} bits" for k in bits) + " |", "|---|" + "---|" * len(bits)]
        for n in names:
            lines.append(f"| {n} | " + " | ".join(_pct(res[k][fn]["bit_acc"][n]) if fn in res[k] else "-"
                                                  for k in bits) + " |")

        def ft_cell(k: int, fn: str = fn) -> str:
            if fn not in res[k]:
                return "-"
            r = res[k][fn]
            return (f"{r.get('ft_s_total', r['config']['ft_s']):.0f} s, {r['ft_steps']} steps, MLP "
                    f"{r['config'].get('template_mlp') or 0}" + (", clean chunk" if r["config"].get("ft_clean_chunk")
                                                                   else ""))

        lines.append("| fine-tune (whole chain) | " + " | ".join(ft_cell(k) for k in bits) + " |")
    refine_names = sorted({n for k in bits for n in res[k] if "_ft_refine" in n},
                          key=lambda n: int(n.split("refine")[1]))
    for fn in refine_names:
        f0 = next(res[k][fn] for k in bits if fn in res[k])
        rf = f0["refine"]
        lines += ["", f"The fine-tuned encoder's residual refined by {rf['steps']} Adam steps against the frozen "
                      f"decoder (`gsw.mark.refine.refine_residual`: lr {rf['lr']} "
                      f"{rf.get('schedule', 'constant')}, logit margin {rf['margin']}, "
                      f"PSNR kept at {f0['psnr']:.1f} dB"
                      + ((", loss on the clean image and through one training noise layer "
                          + ("per step" if rf.get("eot_every", 1) == 1 else f"every {rf['eot_every']} steps")
                          + ", in turn") if rf["eot"] else ", clean loss only")
                      + f"; what an image-space embedding with the shipped decoder does), {f0['n']} pairs:", "",
                  "| attack | " + " | ".join(f"{k} bits" for k in bits) + " |", "|---|" + "---|" * len(bits)]
        for n in names:
            lines.append(f"| {n} | " + " | ".join(_pct(res[k][fn]["bit_acc"][n]) if fn in res[k] else "-"
                                                  for k in bits) + " |")
    rc = {k: res[k]["pair_ft_cpu_recheck"] for k in bits if "pair_ft_cpu_recheck" in res[k]}
    if rc:
        lines += [""] + [f"CPU re-check, {k} bits (the encoder of the fine-tune chain's "
                         f"{r['encoder']['ft_s_total']:.0f}-s stage, templates {r['encoder']['templates']} + MLP width "
                         f"{r['encoder']['template_mlp']}, {_pct(r['encoder']['pair_on_gpu'])} % clean on the GPU; with "
                         f"the shipped decoder as `load_decoder` loads it, new messages, {r['n']} pairs): clean "
                         f"{_pct(r['bit_acc']['identity'])} % (95 % "
                         f"bootstrap over photos {_pct(r['identity_ci95'][0])}-{_pct(r['identity_ci95'][1])}), "
                         "training layers " + ", ".join(f"{a} {_pct(v)}" for a, v in r["bit_acc"].items()
                                                        if a != "identity") + " %."
                         for k, r in rc.items()]
    lines += ["", "Training noise layers (random draw from the range, strength 1): crop keeps 35-100 % of the area; "
                  "resize x0.5-1; JPEG q50-90; blur sigma 0.1-2 px; noise std 0-0.08; rotation 0-15 deg; "
                  "combined = crop (50-100 %) + blur (0.1-1) + JPEG (60-90). Paper attacks: fixed parameters as named.",
              "", "### Unmarked val photos, whitened decoder, x 1,000 random messages", "",
              "| | " + " | ".join(f"{k} bits" for k in bits) + " |", "|---|" + "---|" * len(bits)]
    U = {k: rep["runs"][str(k)]["results"]["unbiased_whitened"] for k in bits}
    R = {k: rep["runs"][str(k)]["results"]["unbiased_raw"] for k in bits}
    rows = [
        ("mean bit acc vs messages (%) (target 50 +- 2)", lambda k: _pct(U[k]["mean_bit_acc"])),
        ("same, raw decoder (%)", lambda k: _pct(R[k]["mean_bit_acc"])),
        ("per-bit P(bit=1), max abs dev from 0.5, 100 photos (target <= 0.05)",
         lambda k: f"{U[k]['per_bit_p1_max_dev']:.3f}"),
        ("same for a perfectly fair decoder (simulated: the measurement floor with 100 photos)",
         lambda k: f"{U[k].get('per_bit_p1_max_dev_if_fair', float('nan')):.3f}"),
        ("same for a fair decoder centred on the 200 train photos (simulated floor: fitting + evaluation noise)",
         lambda k: f"{U[k].get('per_bit_p1_max_dev_if_fair_fitted', float('nan')):.3f}"),
        ("P(a fair decoder centred on 200 photos deviates this much): p-value",
         lambda k: f"{U[k].get('per_bit_p1_max_dev_p_value_fitted', float('nan')):.3f}"),
        ("same, raw decoder", lambda k: f"{R[k]['per_bit_p1_max_dev']:.3f}"),
        ("same, 1,000 random crops of the val photos (crops of one photo are correlated)",
         lambda k: f"{U[k]['views_per_bit_p1_max_dev']:.3f}"),
        ("per-bit acc vs messages, min-max (%)",
         lambda k: f"{_pct(U[k]['per_bit_acc_vs_messages_min'])}-{_pct(U[k]['per_bit_acc_vs_messages_max'])}"),
        ("mean abs correlation between bits (raw -> whitened)",
         lambda k: f"{R[k]['mean_abs_bit_corr']:.3f} -> {U[k]['mean_abs_bit_corr']:.3f}"),
        ("FP threshold (matching bits, P <= 1e-6)", lambda k: f"{U[k]['fp_threshold']} ({U[k]['fp_threshold_prob']:.1e})"),
        ("pairs reaching it, of 100 x 1,000 (target 0)", lambda k: str(U[k]["false_positives"])),
        ("most matching bits seen", lambda k: str(U[k]["max_matching_bits"])),
        ("CPU re-check of the exported file: mean acc / FP",
         lambda k: f"{_pct(rep['cpu_recheck'][str(k)]['mean_bit_acc'])} / {rep['cpu_recheck'][str(k)]['false_positives']}"),
    ]
    for name, f in rows:
        lines.append(f"| {name} | " + " | ".join(f(k) for k in bits) + " |")
    jf = rep["jpeg_fidelity"]
    lines += ["", f"### kornia differentiable JPEG vs real JPEG (libjpeg-turbo 4:2:0), PSNR dB, "
                  f"{jf['num_images']} val crops 256x256", "",
              "| quality | real vs original | diff vs original | diff vs real |", "|---|---|---|---|"]
    for q, v in jf["psnr_db"].items():
        lines.append(f"| {q} | {v['real_vs_orig']:.2f} | {v['diff_vs_orig']:.2f} | {v['diff_vs_real']:.2f} |")
    lines += ["", "The differentiable codec is about 1 dB milder than the real one but ~10 dB closer to it than "
                  "the real codec is to the input; training uses the real codec in the forward pass and kornia's "
                  "gradient (`real_diffgrad`) in the old trainer; `train_multi` uses the differentiable codec alone "
                  "(no CPU work per step); evaluation uses the real codec only.", ""]
    lines += ["### Status against the targets", ""]
    train_names = [n for n in names if not any(c.isdigit() for c in n)]
    for k in bits:
        pairs = []
        for fn, label in (("pair_raw", "jointly trained encoder"),
                          *((n, f"encoder fine-tuned ({n})") for n in ft_names if n in res[k]),
                          *((n, f"fine-tuned encoder + {res[k][n]['refine']['steps']} refinement steps")
                            for n in refine_names if n in res[k])):
            b = res[k][fn]["bit_acc"]
            worst = min(train_names, key=lambda n: b[n])
            ok_clean, ok_noise = b["identity"] >= 0.995, all(b[n] >= 0.90 for n in train_names)
            pairs.append(f"{label}: clean {100 * b['identity']:.2f} % ({'met' if ok_clean else 'NOT met'}, >= 99.5), "
                         f"worst training noise layer {worst} {_pct(b[worst])} % "
                         f"({'met' if ok_noise else 'NOT met'}, >= 90)")
        u = U[k]
        lines.append(f"- {k} bits: " + "; ".join(pairs)
                     + f"; unbiased mean {_pct(u['mean_bit_acc'])} % and {u['false_positives']} false positives "
                     f"({'met' if abs(u['mean_bit_acc'] - 0.5) <= 0.02 and u['false_positives'] == 0 else 'NOT met'}); "
                     f"per-bit P(1) max dev {u['per_bit_p1_max_dev']:.2f} "
                     f"({'met' if u['per_bit_p1_max_dev'] <= 0.05 else 'NOT met'}, <= 0.05; a fair decoder shows "
                     f"{u.get('per_bit_p1_max_dev_if_fair', float('nan')):.2f} on 100 photos, "
                     f"{u.get('per_bit_p1_max_dev_if_fair_fitted', float('nan')):.2f} when centred on 200; "
                     f"p = {u.get('per_bit_p1_max_dev_p_value_fitted', float('nan')):.3f}).")
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
