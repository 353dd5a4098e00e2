"""Export pre-trained decoders into a weights folder and write the decoder report (``gsw decoder export``).

* :func:`export_run` - the decoders (+ whitening) of a run folder (:mod:`gsw.decoder.pretrain.runs`) saved
  as ``hidden_k{bits}.pt`` with :func:`gsw.decoder.zoo.save_decoder` and recorded in the folder's
  ``manifest.json`` (sha256, size, provenance); optionally the whitening is refitted here on the CPU in
  float32; the exported files are re-checked through :func:`gsw.decoder.zoo.load_decoder`.
* :func:`export_shipped` - the shipped decoders re-saved from their own files (byte-identical when torch
  writes the same bytes) and their statistics on unmarked photos re-measured on the CPU; the training
  records, which no weight file holds, come from a previous report.
* :func:`merge_ft_runs`, :func:`cpu_pair_recheck` - encoder fine-tunes of the shipped decoders in the report.
* :func:`write_report` - ``STEM.json`` and ``STEM.md`` (:func:`gsw.decoder.pretrain.report.markdown`).

Every statistic of unmarked photos is :func:`~gsw.decoder.pretrain.evaluation.unbiasedness` with 1,000
messages drawn from seed 2, on the CPU: deterministic for a given torch build.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gsw._atomic import atomic_write
from gsw.attacks.layers import diff_jpeg, real_jpeg, training_noise_layers
from gsw.decoder.pretrain.data import image_bank, load_split, photo_paths
from gsw.decoder.pretrain.encoders import embed_scaled, load_run_encoder
from gsw.decoder.pretrain.evaluation import eval_attacks, unbiasedness
from gsw.decoder.pretrain.report import markdown
from gsw.decoder.pretrain.runs import load_run_decoder, read_meta
from gsw.decoder.pretrain.whiten import fit_whitening_multi
from gsw.decoder.whitening import WhiteningLayer
from gsw.decoder.zoo import WatermarkDecoder, load_decoder, read_provenance, record_in_manifest, save_decoder, weights_path
from gsw.stats import bootstrap_ci95

__all__ = ["RUN_KEYS", "cpu_pair_recheck", "export_run", "export_shipped", "jpeg_fidelity", "measure_unbiased",
           "merge_ft_runs", "write_report"]

Report = dict[str, Any]

#: The entries of a run's metadata that the report keeps.
RUN_KEYS = ("steps", "steps_per_s", "train_elapsed_s", "wall_s", "device", "torch", "python", "config", "args",
            "results", "whitening_fit_samples", "num_train_images", "val_log", "train_log", "whitening_refit")
#: Random messages and their seed in every unmarked-photo statistic of the report.
NUM_MESSAGES, MESSAGE_SEED = 1000, 2
#: What the provenance of an exported decoder says about its data.
DATA_NOTE = "bsds500/train (200 photos), whitening on the same photos"


def jpeg_fidelity(images: list[torch.Tensor], qualities: tuple[int, ...] = (90, 70, 50, 30)) -> dict[str, Any]:
    """PSNR (dB) of real JPEG vs original, kornia's differentiable JPEG vs original, and differentiable vs
    real, on the top-left ``side`` x ``side`` crops of the photos (uint8 [3,H,W]); ``side`` is 256, or the
    smallest photo side when a photo is smaller."""
    side = min(256, *(min(img.shape[-2:]) for img in images))
    x = torch.stack([img[:, :side, :side] for img in images]).float() / 255
    ps = lambda a, b: float(-10 * torch.log10((a - b).pow(2).mean()))  # noqa: E731
    out = {}
    for q in qualities:
        qt = torch.full((x.shape[0],), float(q))
        r, d = real_jpeg(x, qt), diff_jpeg(x, qt)
        out[str(q)] = {"real_vs_orig": ps(r, x), "diff_vs_orig": ps(d, x), "diff_vs_real": ps(d, r)}
    return {"num_images": int(x.shape[0]), "side": side, "psnr_db": out}


@torch.no_grad()
def measure_unbiased(model: WatermarkDecoder, val_images: list[torch.Tensor], num_fit: int) -> dict[str, Any]:
    """The report's unmarked-photo statistics of a decoder file: ``unbiased_whitened`` (with 10 random crops
    per photo and the floor for a centre fitted on ``num_fit`` photos), ``unbiased_raw`` (before whitening)
    and ``cpu_recheck`` (whitened, photos only)."""
    k = model.num_bits
    return {"unbiased_whitened": unbiasedness(model, val_images, k, NUM_MESSAGES, seed=MESSAGE_SEED, extra_views=10,
                                              fit_images=num_fit),
            "unbiased_raw": unbiasedness(model.decoder, val_images, k, NUM_MESSAGES, seed=MESSAGE_SEED),
            "cpu_recheck": unbiasedness(model, val_images, k, NUM_MESSAGES, seed=MESSAGE_SEED)}


def _refit(dec: torch.nn.Module, meta: dict[str, Any], train_images: list[torch.Tensor],
           val_images: list[torch.Tensor], num_crops: int, eps: float) -> WhiteningLayer:
    """Refit the whitening on the CPU (float32) and re-measure the run's unbiasedness with it (in ``meta``)."""
    k = dec.num_bits
    with torch.no_grad():
        (wl,), nfit = fit_whitening_multi([dec], train_images, image_bank(train_images, "cpu"),
                                          num_crops=num_crops, eps=eps)
        meta["results"]["unbiased_whitened"] = unbiasedness(lambda ll: wl(dec(ll)), val_images, k, NUM_MESSAGES,
                                                            seed=MESSAGE_SEED, extra_views=10,
                                                            fit_images=len(train_images))
        meta["results"]["unbiased_raw"] = unbiasedness(dec, val_images, k, NUM_MESSAGES, seed=MESSAGE_SEED)
    meta["results"].pop("pair_whitened_before_ft", None)  # measured with the replaced whitening
    meta["whitening_refit"] = {"device": "cpu", "dtype": "float32", "samples": nfit, "eps": eps, "mode": "zca",
                               "center": "median"}
    meta["whitening_fit_samples"] = nfit
    return wl


def export_run(run: str | Path, data: str | Path, weights_dir: str | Path, bits: tuple[int, ...],
               previous: Report | None = None, refit_whitening: bool = False, whiten_crops: int = 1600,
               whiten_eps: float = 1e-3, log: Callable[[str], None] = lambda _: None) -> Report:
    """Save the decoders of ``run`` for ``bits`` into ``weights_dir`` (+ manifest) and build the report.

    Args:
        data: the photo folder (``val/`` for the statistics, ``train/`` for a refit).
        previous: an earlier report whose entries for other bit lengths are kept.
        refit_whitening: refit each whitening here (``whiten_crops`` random crops, eigenvalue floor ``whiten_eps``).
        log: receives a line as each stage starts.

    Returns:
        the report (``runs``, ``cpu_recheck``, ``jpeg_fidelity``).
    """
    run, weights_dir = Path(run), Path(weights_dir)
    val_images = load_split(data, "val")
    train_images = load_split(data, "train") if refit_whitening else []
    report: Report = {"runs": {}, "cpu_recheck": {}}
    if previous is not None:  # the bit lengths not exported now keep their entries
        report = {key: {b: v for b, v in previous.get(key, {}).items() if int(b) not in bits} for key in report}
    for k in bits:
        log(f"{k} bits: exporting {run}")
        dec, wl, meta = load_run_decoder(run, k)
        if refit_whitening:
            wl = _refit(dec, meta, train_images, val_images, whiten_crops, whiten_eps)
        prov = {"steps": meta["steps"], "train_s": round(meta["train_elapsed_s"]), "device": meta["device"],
                "torch": meta["torch"], "data": DATA_NOTE}
        path = weights_path(k, weights_dir)
        save_decoder(dec, wl, path, meta=prov)
        record_in_manifest(path, prov)  # the other bit lengths' entries stay
        report["runs"][str(k)] = {x: meta[x] for x in RUN_KEYS if x in meta}
    for k in bits:  # the exported files, through the public loader, on the CPU
        log(f"{k} bits: re-checking the exported file")
        with torch.no_grad():
            report["cpu_recheck"][str(k)] = unbiasedness(load_decoder(k, weights_dir=weights_dir), val_images, k,
                                                         NUM_MESSAGES, seed=MESSAGE_SEED)
    log("JPEG fidelity")
    report["jpeg_fidelity"] = jpeg_fidelity(val_images)
    return report


def _changes(old: dict[str, Any], new: dict[str, Any], where: str) -> list[str]:
    return [f"{where}.{n}: {old[n]!r} -> {new[n]!r}" for n in old if n in new and old[n] != new[n]]


def export_shipped(previous: Report, data: str | Path, weights_dir: str | Path, bits: tuple[int, ...],
                   source_dir: str | Path | None = None,
                   log: Callable[[str], None] = lambda _: None) -> tuple[Report, list[str]]:
    """Re-save the shipped decoders into ``weights_dir`` (+ manifest) and re-measure them into ``previous``.

    Each decoder is loaded (checksum-verified) from ``source_dir`` (default: the package's weights) and saved
    with the provenance its file holds; its unmarked-photo statistics (:func:`measure_unbiased`, on the
    ``data/val`` photos, centre floor for the number of ``data/train`` photos) and the JPEG fidelity replace
    those of ``previous``, whose other entries (the training records) stay. ``log`` receives a line as each
    stage starts.

    Returns:
        the new report and the values that changed (``"32 bits: unbiased_raw.mean_bit_acc: 0.5 -> 0.6"``).

    Raises:
        ValueError: ``previous`` has no run record for a bit length of ``bits``.
    """
    rep = copy.deepcopy(previous)
    missing = [k for k in bits if str(k) not in rep.get("runs", {})]
    if missing:
        raise ValueError(f"the previous report has no run record for {missing} bits (the training records of the "
                         "shipped decoders come from it)")
    val_images = load_split(data, "val")
    num_fit = len(photo_paths(Path(data) / "train"))
    changes: list[str] = []
    rep.setdefault("cpu_recheck", {})
    for k in bits:
        model = load_decoder(k, weights_dir=source_dir)
        prov = read_provenance(weights_path(k, source_dir))
        path = weights_path(k, weights_dir)
        save_decoder(model.decoder, model.whitening, path, meta=prov)
        record_in_manifest(path, prov)
        log(f"{k} bits: measuring {len(val_images)} unmarked photos")
        stats = measure_unbiased(model, val_images, num_fit)
        results = rep["runs"][str(k)]["results"]
        for name in ("unbiased_whitened", "unbiased_raw"):
            changes += _changes(results.get(name, {}), stats[name], f"{k} bits: {name}")
            results[name] = stats[name]
        changes += _changes(rep["cpu_recheck"].get(str(k), {}), stats["cpu_recheck"], f"{k} bits: cpu_recheck")
        rep["cpu_recheck"][str(k)] = stats["cpu_recheck"]
    log("JPEG fidelity")
    jf = jpeg_fidelity(val_images)
    changes += _changes(rep.get("jpeg_fidelity", {}), jf, "jpeg_fidelity")
    rep["jpeg_fidelity"] = jf
    return rep, changes


def merge_ft_runs(rep: Report, ft_runs: list[str | Path], bits: tuple[int, ...]) -> None:
    """Copy the fine-tuned pairs' evaluations (``*_ft``, ``*_ft_refine*``) of encoder-only fine-tune runs
    of the shipped decoders into the report's run records, with their settings and device."""
    for k in bits:
        run = rep["runs"][str(k)]
        for ft_dir in ft_runs:
            if not (Path(ft_dir) / f"k{k}.json").exists():
                continue
            meta = read_meta(ft_dir, k)
            for name, r in meta["results"].items():
                if name.endswith("_ft") or "_ft_refine" in name:
                    run["results"][name] = {**r, "config": {c: meta["config"].get(c) for c in
                                                            ("ft_s", "ft_lr", "ft_view_warp", "ft_target",
                                                             "templates", "template_mlp", "ft_clean_chunk")},
                                            "ft_steps": meta.get("ft_steps_total", meta.get("ft_steps")),
                                            "ft_s_total": meta.get("ft_s_total", meta["config"].get("ft_s")),
                                            "device": meta["device"]}


@torch.no_grad()
def cpu_pair_recheck(run: str | Path, k: int, val_images: list[torch.Tensor], msgs_per_image: int = 4,
                     weights_dir: str | Path | None = None) -> dict[str, Any]:
    """The fine-tuned encoder of ``run`` with the shipped raw decoder (loaded and checksum-checked by
    ``load_decoder``) on every val photo, messages drawn anew (seed 1000 + photo index), every training noise
    layer with the real codec; clean accuracy with a 95 % bootstrap interval over photos."""
    meta = read_meta(run, k)
    enc, cfg = load_run_encoder(run, k)
    dec = load_decoder(k, weights_dir=weights_dir).decoder
    attacks = dict(training_noise_layers("real"))
    per: dict[str, list[float]] = {a: [] for a in attacks}
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


def write_report(rep: Report, stem: str | Path) -> tuple[Path, Path]:
    """Write ``stem.json`` and ``stem.md`` (every bit length of the report, in increasing order) atomically;
    returns their paths."""
    stem = Path(stem)
    js, md = stem.parent / (stem.name + ".json"), stem.parent / (stem.name + ".md")
    stem.parent.mkdir(parents=True, exist_ok=True)
    text = markdown(rep, sorted(int(b) for b in rep["runs"]))
    with atomic_write(js, "w") as f:
        f.write(json.dumps(rep, indent=1))
    with atomic_write(md, "w") as f:
        f.write(text)
    return js, md
