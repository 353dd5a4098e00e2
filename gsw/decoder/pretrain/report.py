"""The decoder report in markdown (``benchmarks/results/decoder.md``), rendered from its JSON.

The JSON (``{"runs": {bits: run record}, "cpu_recheck": {bits: unbiasedness}, "jpeg_fidelity": ...}``) is
what :mod:`gsw.decoder.pretrain.export` writes; :func:`markdown` is a pure function of it.
"""

from __future__ import annotations

from typing import Any

__all__ = ["markdown"]

Report = dict[str, Any]


def _pct(v: float) -> str:
    return f"{100 * v:.1f}"


def _intro(rep: Report, bits: list[int]) -> list[str]:
    """Title and the paragraph on how the decoders were trained and whitened."""
    r0 = rep["runs"][str(bits[0])]
    cfg = r0["config"]
    a0 = r0.get("args", {})
    wmode, wcenter = a0.get("whiten_mode", "pca").upper(), a0.get("whiten_center", "mean")
    cont = (f" The run continued an earlier one (`--init`: warm restart with a new optimizer and schedule, lr "
            f"{cfg['lr']}, no curriculum); steps and time are totals over the chain of runs." if a0.get("init") else "")
    balanced = [k for k in bits if rep["runs"][str(k)]["config"].get("balance", 0) > 0]
    return [
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
           + ", ".join(str(k) for k in balanced) + " bits; " if balanced else "")
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


def _table(res: dict[int, Any], fn: str, names: list[str], bits: list[int]) -> list[str]:
    """Bit accuracy per attack (rows) and bit length (columns) of the evaluation ``fn`` ("-" where missing)."""
    return (["| attack | " + " | ".join(f"{k} bits" for k in bits) + " |", "|---|" + "---|" * len(bits)]
            + [f"| {n} | " + " | ".join(_pct(res[k][fn]["bit_acc"][n]) if fn in res[k] else "-" for k in bits) + " |"
               for n in names])


def _ft_cell(r: dict[str, Any] | None) -> str:
    if r is None:
        return "-"
    return (f"{r.get('ft_s_total', r['config']['ft_s']):.0f} s, {r['ft_steps']} steps, MLP "
            f"{r['config'].get('template_mlp') or 0}" + (", clean chunk" if r["config"].get("ft_clean_chunk") else ""))


def _ft_tables(res: dict[int, Any], ft_names: list[str], names: list[str], bits: list[int]) -> list[str]:
    """One table per encoder fine-tune against the frozen decoder."""
    lines: list[str] = []
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
                      f"PSNR {f0['psnr']:.1f} dB:", ""]
        lines += _table(res, fn, names, bits)
        lines.append("| fine-tune (whole chain) | " + " | ".join(_ft_cell(res[k].get(fn)) for k in bits) + " |")
    return lines


def _refine_tables(res: dict[int, Any], refine_names: list[str], names: list[str], bits: list[int]) -> list[str]:
    """One table per refinement of the fine-tuned encoder's residual."""
    lines: list[str] = []
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
                      + f"; what an image-space embedding with the shipped decoder does), {f0['n']} pairs:", ""]
        lines += _table(res, fn, names, bits)
    return lines


def _cpu_recheck_lines(res: dict[int, Any], bits: list[int]) -> list[str]:
    rc = {k: res[k]["pair_ft_cpu_recheck"] for k in bits if "pair_ft_cpu_recheck" in res[k]}
    if not rc:
        return []
    return [""] + [f"CPU re-check, {k} bits (the encoder of the fine-tune chain's "
                   f"{r['encoder']['ft_s_total']:.0f}-s stage, templates {r['encoder']['templates']} + MLP width "
                   f"{r['encoder']['template_mlp']}, {_pct(r['encoder']['pair_on_gpu'])} % clean on the GPU; with "
                   f"the shipped decoder as `load_decoder` loads it, new messages, {r['n']} pairs): clean "
                   f"{_pct(r['bit_acc']['identity'])} % (95 % "
                   f"bootstrap over photos {_pct(r['identity_ci95'][0])}-{_pct(r['identity_ci95'][1])}), "
                   "training layers " + ", ".join(f"{a} {_pct(v)}" for a, v in r["bit_acc"].items()
                                                  if a != "identity") + " %."
                   for k, r in rc.items()]


def _unbiased_table(rep: Report, bits: list[int]) -> list[str]:
    """Statistics of the unmarked val photos against random messages."""
    lines = ["", "Training noise layers (random draw from the range, strength 1): crop keeps 35-100 % of the area; "
                 "resize x0.5-1; JPEG q50-90; blur sigma 0.1-2 px; noise std 0-0.08; rotation 0-15 deg; "
                 "combined = crop (50-100 %) + blur (0.1-1) + JPEG (60-90). Paper attacks: fixed parameters as named.",
             "", "### Unmarked val photos, whitened decoder, x 1,000 random messages", "",
             "| | " + " | ".join(f"{k} bits" for k in bits) + " |", "|---|" + "---|" * len(bits)]
    U = {k: rep["runs"][str(k)]["results"]["unbiased_whitened"] for k in bits}
    R = {k: rep["runs"][str(k)]["results"]["unbiased_raw"] for k in bits}
    C = {k: rep["cpu_recheck"][str(k)] for k in bits}
    nan = float("nan")
    rows = [
        ("mean bit acc vs messages (%) (target 50 +- 2)", lambda k: _pct(U[k]["mean_bit_acc"])),
        ("same, raw decoder (%)", lambda k: _pct(R[k]["mean_bit_acc"])),
        ("per-bit P(bit=1), max abs dev from 0.5, 100 photos (target <= 0.05)",
         lambda k: f"{U[k]['per_bit_p1_max_dev']:.3f}"),
        ("same for a perfectly fair decoder (simulated: the measurement floor with 100 photos)",
         lambda k: f"{U[k].get('per_bit_p1_max_dev_if_fair', nan):.3f}"),
        ("same for a fair decoder centred on the 200 train photos (simulated floor: fitting + evaluation noise)",
         lambda k: f"{U[k].get('per_bit_p1_max_dev_if_fair_fitted', nan):.3f}"),
        ("P(a fair decoder centred on 200 photos deviates this much): p-value",
         lambda k: f"{U[k].get('per_bit_p1_max_dev_p_value_fitted', nan):.3f}"),
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
         lambda k: f"{_pct(C[k]['mean_bit_acc'])} / {C[k]['false_positives']}"),
    ]
    return lines + [f"| {name} | " + " | ".join(f(k) for k in bits) + " |" for name, f in rows]


def _jpeg_lines(rep: Report) -> list[str]:
    jf = rep["jpeg_fidelity"]
    lines = ["", f"### kornia differentiable JPEG vs real JPEG (libjpeg-turbo 4:2:0), PSNR dB, "
                 f"{jf['num_images']} val crops {jf.get('side', 256)}x{jf.get('side', 256)}", "",
             "| quality | real vs original | diff vs original | diff vs real |", "|---|---|---|---|"]
    for q, v in jf["psnr_db"].items():
        lines.append(f"| {q} | {v['real_vs_orig']:.2f} | {v['diff_vs_orig']:.2f} | {v['diff_vs_real']:.2f} |")
    return lines + ["", "The differentiable codec is about 1 dB milder than the real one but ~10 dB closer to it than "
                        "the real codec is to the input; training uses the real codec in the forward pass and kornia's "
                        "gradient (`real_diffgrad`) in the old trainer; `train_multi` uses the differentiable codec "
                        "alone (no CPU work per step); evaluation uses the real codec only.", ""]


def _pair_status(res: dict[str, Any], evaluations: list[tuple[str, str]], train_names: list[str]) -> list[str]:
    pairs = []
    for fn, label in evaluations:
        b = res[fn]["bit_acc"]
        worst = min(train_names, key=lambda n: b[n])
        ok_clean, ok_noise = b["identity"] >= 0.995, all(b[n] >= 0.90 for n in train_names)
        pairs.append(f"{label}: clean {100 * b['identity']:.2f} % ({'met' if ok_clean else 'NOT met'}, >= 99.5), "
                     f"worst training noise layer {worst} {_pct(b[worst])} % "
                     f"({'met' if ok_noise else 'NOT met'}, >= 90)")
    return pairs


def _status_lines(rep: Report, res: dict[int, Any], bits: list[int], names: list[str], ft_names: list[str],
                  refine_names: list[str]) -> list[str]:
    """Each bit length against the targets (pair accuracy, unbiasedness, false positives)."""
    lines = ["### Status against the targets", ""]
    train_names = [n for n in names if not any(c.isdigit() for c in n)]
    for k in bits:
        evaluations = [("pair_raw", "jointly trained encoder"),
                       *((n, f"encoder fine-tuned ({n})") for n in ft_names if n in res[k]),
                       *((n, f"fine-tuned encoder + {res[k][n]['refine']['steps']} refinement steps")
                         for n in refine_names if n in res[k])]
        u = rep["runs"][str(k)]["results"]["unbiased_whitened"]
        nan = float("nan")
        lines.append(f"- {k} bits: " + "; ".join(_pair_status(res[k], evaluations, train_names))
                     + f"; unbiased mean {_pct(u['mean_bit_acc'])} % and {u['false_positives']} false positives "
                     f"({'met' if abs(u['mean_bit_acc'] - 0.5) <= 0.02 and u['false_positives'] == 0 else 'NOT met'}); "
                     f"per-bit P(1) max dev {u['per_bit_p1_max_dev']:.2f} "
                     f"({'met' if u['per_bit_p1_max_dev'] <= 0.05 else 'NOT met'}, <= 0.05; a fair decoder shows "
                     f"{u.get('per_bit_p1_max_dev_if_fair', nan):.2f} on 100 photos, "
                     f"{u.get('per_bit_p1_max_dev_if_fair_fitted', nan):.2f} when centred on 200; "
                     f"p = {u.get('per_bit_p1_max_dev_p_value_fitted', nan):.3f}).")
    return lines + [""]


def markdown(rep: Report, bits: list[int]) -> str:
    """The markdown report of the decoders of ``bits`` (columns, in this order) from the report JSON ``rep``."""
    res = {k: rep["runs"][str(k)]["results"] for k in bits}
    names = list(res[bits[0]]["pair_raw"]["bit_acc"].keys())
    lines = _intro(rep, bits) + _table(res, "pair_raw", names, bits)
    lines.append("| PSNR of marked photos (dB) | " + " | ".join(f"{res[k]['pair_raw']['psnr']:.1f}" for k in bits) + " |")
    ft_names = [n for n in ("pair_whitened_ft", "pair_raw_ft") if any(n in res[k] for k in bits)]
    refine_names = sorted({n for k in bits for n in res[k] if "_ft_refine" in n}, key=lambda n: int(n.split("refine")[1]))
    lines += _ft_tables(res, ft_names, names, bits) + _refine_tables(res, refine_names, names, bits)
    lines += _cpu_recheck_lines(res, bits) + _unbiased_table(rep, bits) + _jpeg_lines(rep)
    lines += _status_lines(rep, res, bits, names, ft_names, refine_names)
    return "\n".join(lines)
