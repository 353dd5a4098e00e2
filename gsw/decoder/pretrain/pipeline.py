"""Pre-train, whiten and evaluate the HiDDeN watermark decoders, all bit lengths in one process
(``gsw decoder train``).

1. :func:`~gsw.decoder.pretrain.multi.train_multi`: one encoder/decoder pair per bit length, all fed the
   same batches of random crops (+ flips) of the training photos (``DATA/train``), which stay on the device;
   device-only attacks; curriculum: no attacks and a strong watermark (``psnr_start``) for the first
   ``clean_frac`` of the run, then the attacks ramp in and the PSNR tightens to ``psnr``. Budgeted by steps
   or by wall time (``time_budget_s``); ``init`` continues from an earlier run (a warm restart with a new
   optimizer and learning-rate schedule: pass ``clean_frac=0`` and ``psnr_start=psnr`` to skip the curriculum).
2. Whitening of each decoder on unmarked photos (the training photos, mirrored, + random crops); ZCA with
   median centring by default, or the package's whitening (``shipped_whitening``, shipped decoders only).
3. Evaluation on the ``DATA/val`` photos at full size (real JPEG): encoder + raw decoder under every training
   noise layer and the paper's attacks; unbiasedness and false positives of the whitened and raw decoders
   (val photos x ``num_messages`` messages); then the encoders alone are fine-tuned for ``ft_s`` seconds
   against the frozen whitened decoders and evaluated again; ``refine_steps``: the last encoders' residuals
   refined against the frozen decoder (:func:`gsw.mark.refine.refine_residual`) and evaluated like the pairs.
4. The run folder (:mod:`gsw.decoder.pretrain.runs`) is rewritten as soon as each stage ends;
   ``deadline_s`` shortens the later stages to end in time; ``half`` rounds every encoder to float16 before
   it is evaluated and keeps only the last one.

:func:`gsw.decoder.pretrain.export.export_run` then writes the package weights, manifest and report.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from gsw.attacks.layers import GpuAttacks, paper_attacks, training_noise_layers
from gsw.decoder.dwt import ll_subband
from gsw.decoder.hidden import bit_accuracy
from gsw.decoder.pretrain.config import WHITEN_EIG_FLOOR, MultiConfig
from gsw.decoder.pretrain.data import bank_crops, image_bank, load_split
from gsw.decoder.pretrain.encoders import embed_scaled, encoder_residual, to_half
from gsw.decoder.pretrain.evaluation import eval_attacks_chunked, unbiasedness
from gsw.decoder.pretrain.multi import describe_entry, train_multi
from gsw.decoder.pretrain.runs import config_dict, load_init, read_meta, write_stage
from gsw.decoder.pretrain.whiten import fit_whitening_multi, shipped_whitening
from gsw.decoder.whitening import WhiteningLayer
from gsw.progress import Progress

__all__ = ["PretrainOptions", "pretrain"]


@dataclasses.dataclass
class PretrainOptions:
    """Everything :func:`pretrain` does; recorded as ``args`` in the run's metadata."""

    data: str  # folder with train/ and val/ photo folders
    output: str  # the run folder
    bits: tuple[int, ...] = (32, 48, 64)
    steps: int = 1000  # training steps (when no time budget)
    time_budget_s: float | None = None  # training wall time (all bit lengths); wins over steps
    device: str = "cpu"
    seed: int = 0
    amp: str = "auto"  # bf16 autocast: auto (on CUDA), on, off
    # networks
    channels: int = 64
    enc_blocks: int = 4
    dec_blocks: int = 8
    dec_norm: str = "standardize"
    enc_down: int = 2  # encoder resolution divisor (training aid)
    templates: int = 0  # > 0: on/off template encoder aid of this side
    template_mlp: int = 0
    template_refine: int = 0
    # joint training
    batch: int = 64  # per bit length
    crop: int = 128
    lr: float = 1e-3
    psnr: float = 30.0
    psnr_start: float = 22.0
    clean_frac: float = 0.3
    noise_ramp_end: float = 0.6
    clean_chunk: bool = False
    view_warp: bool = False
    balance: float = 0.0
    balance_batch: int = 16
    freeze_bn: bool = False
    init: str | None = None  # an earlier run folder to continue from
    init_encoder: str = "encoder"  # or "encoder_ft"
    log_every: int = 200
    val_every_s: float = 60.0
    # whitening
    shipped_whitening: bool = False
    whiten_mode: str = "zca"
    whiten_center: str = "median"
    whiten_eps: float = WHITEN_EIG_FLOOR
    whiten_crops: int = 4000
    # encoder fine-tune against the frozen decoders
    ft_s: float = 25.0
    ft_lr: float = 5e-4
    ft_warp: str = "same"  # same (as in training), on, off
    ft_target: str = "whitened"  # or "raw"
    ft_clean_chunk: bool = False
    # evaluation
    eval_images: int = 100
    msgs_per_image: int = 4
    num_messages: int = 1000
    limit_images: int | None = None
    skip_init_eval: bool = False
    refine_steps: tuple[int, ...] = ()
    refine_lr: float = 0.3
    refine_schedule: str = "cosine"
    refine_margin: float = 0.0
    refine_eot: bool = False
    refine_eot_every: int = 1
    refine_fp32: bool = False
    # output
    half: bool = False
    deadline_s: float = 1e9

    def multi_config(self, device: torch.device) -> MultiConfig:
        """The :class:`MultiConfig` of the joint training."""
        amp = (device.type == "cuda") if self.amp == "auto" else self.amp == "on"
        budget = self.time_budget_s if self.time_budget_s and self.time_budget_s > 0 else None
        return MultiConfig(
            bits=tuple(self.bits), channels=self.channels, enc_blocks=self.enc_blocks, dec_blocks=self.dec_blocks,
            crop=self.crop, batch_size=self.batch, lr=self.lr, psnr_start=self.psnr_start, psnr_target=self.psnr,
            clean_frac=self.clean_frac, noise_ramp_end=self.noise_ramp_end, steps=self.steps,
            time_budget_s=budget, amp=amp, channels_last=device.type == "cuda", seed=self.seed,
            log_every=self.log_every, enc_down=self.enc_down, dec_norm=self.dec_norm, templates=self.templates,
            template_mlp=self.template_mlp, template_refine=self.template_refine, view_warp=self.view_warp,
            balance=self.balance, balance_batch=self.balance_batch, freeze_bn=self.freeze_bn,
            clean_chunk=self.clean_chunk)

    def validate(self) -> None:
        """Raises ValueError naming the first inconsistent option."""
        if not self.bits or any(k < 1 for k in self.bits):
            raise ValueError(f"bits must be positive bit lengths, got {self.bits}")
        if self.refine_eot_every < 1:
            raise ValueError("refine_eot_every must be >= 1")
        if self.init is not None and Path(self.init).resolve() == Path(self.output).resolve():
            raise ValueError(f"the run folder {self.output} cannot be its own init (inputs are never overwritten)")
        for name, allowed in (("init_encoder", ("encoder", "encoder_ft")), ("ft_warp", ("same", "on", "off")),
                              ("ft_target", ("whitened", "raw")), ("amp", ("auto", "on", "off")),
                              ("refine_schedule", ("cosine", "constant"))):
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}")


def make_val_fn(val_bank: torch.Tensor, cfg: MultiConfig) -> Callable[..., dict[str, Any]]:
    """Validation during training: 64 fixed crops of the val photos, each training attack at strength 1
    and the view warp, bit accuracy per bit length."""
    gen = torch.Generator(device=val_bank.device).manual_seed(123)
    crops = bank_crops(val_bank, 64, cfg.crop, gen)
    msgs = {k: torch.randint(0, 2, (64, k), device=val_bank.device, generator=gen).float() for k in cfg.bits}

    def acc(d: torch.nn.Module, y: torch.Tensor, k: int) -> float:
        return round(float(bit_accuracy(d(ll_subband(y.float())).float(), msgs[k]).mean()), 4)

    @torch.no_grad()
    def val_fn(encs: list[torch.nn.Module], decs: list[torch.nn.Module], psnr: float) -> dict[str, Any]:
        att = GpuAttacks(val_bank.device, 7)
        out = {}
        for e, d, k in zip(encs, decs, cfg.bits):
            x_w = embed_scaled(e, crops, msgs[k], psnr, cfg.enc_down)
            out[f"k{k}"] = {n: acc(d, att.apply(n, x_w, 1.0), k) for n in cfg.noise_layers}
            out[f"k{k}"]["view"] = acc(d, att.view(x_w, 1.0), k)
        return out

    return val_fn


def _bar_hook(cfg: MultiConfig, desc: str, enabled: bool,
              log: Callable[[str], None]) -> tuple[Progress, Callable[[float, Any], None]]:
    """A progress bar over the training budget (steps, or seconds) and the ``on_step`` hook that drives it;
    log entries go above the bar, or to ``log`` when the bar is off."""
    total = cfg.steps if cfg.time_budget_s is None else max(1, math.ceil(cfg.time_budget_s))
    bar = Progress(max(1, total), desc, enabled=enabled)

    def hook(frac: float, entry: dict[str, Any] | None) -> None:
        post = {"loss": entry["loss"]} if entry else {}
        bar.update(max(0, round(frac * total) - bar.n), **post)
        if entry:
            line = describe_entry(entry, cfg.bits, desc + " ", entry["elapsed"], entry["psnr"], entry["strength"])
            bar.write(line) if enabled else log(line)

    return bar, hook


class _Pretraining:
    """One :func:`pretrain` run: its stages, in order, and the run folder they rewrite."""

    def __init__(self, opts: PretrainOptions, progress: bool) -> None:
        self.opts, self.progress = opts, progress
        self.t0 = time.perf_counter()
        self.device = torch.device(opts.device)
        self.out = Path(opts.output)
        self.ft_encs: list[torch.nn.Module] | None = None
        self.attacks = dict(training_noise_layers("real"))  # evaluation uses the real codec only
        self.attacks.update(paper_attacks())

    def left(self) -> float:
        """Seconds left before ``deadline_s``."""
        return self.opts.deadline_s - (time.perf_counter() - self.t0)

    def log(self, msg: str) -> None:
        """``msg`` on stderr, with the seconds since the start."""
        print(f"[{time.perf_counter() - self.t0:6.1f}s] {msg}", file=sys.stderr, flush=True)

    def load_data(self) -> None:
        """Photos of ``data/train`` and ``data/val``, their device banks and the training configuration."""
        o, dev = self.opts, self.device
        if dev.type == "cuda":
            torch.backends.cudnn.benchmark = True
            torch.backends.cuda.matmul.allow_tf32 = True
            torch.backends.cudnn.allow_tf32 = True
        self.train_images = load_split(o.data, "train", o.limit_images)
        self.val_images = load_split(o.data, "val", o.limit_images)
        self.bank, self.val_bank = image_bank(self.train_images, dev), image_bank(self.val_images, dev)
        self.log(f"{len(self.train_images)} train / {len(self.val_images)} val photos, bank "
                 f"{tuple(self.bank.shape)} on {dev}")
        self.cfg = o.multi_config(dev)
        self.out.mkdir(parents=True, exist_ok=True)

    def train(self) -> None:
        """Joint training (or the networks of ``init`` as they are, when no step is asked for)."""
        o, cfg = self.opts, self.cfg
        encs0, decs0 = load_init(o.init, cfg, o.init_encoder) if o.init else (None, None)
        self.prev = {k: read_meta(o.init, k) for k in cfg.bits} if o.init else {}
        self.trained = not (o.init and cfg.time_budget_s is None and o.steps <= 0)
        if not self.trained:
            st: dict[str, Any] = {"encoders": [e.to(self.device).eval() for e in encs0],
                                  "decoders": [d.to(self.device).eval() for d in decs0],
                                  "step": 0, "elapsed": 0.0, "log": [], "val": [], "steps_per_s": 0.0}
        else:
            bar, hook = _bar_hook(cfg, "train", self.progress, self.log)
            with bar:
                st = train_multi(cfg, self.bank, encoders=encs0, decoders=decs0,
                                 val_fn=make_val_fn(self.val_bank, cfg), val_every_s=o.val_every_s, verbose=False,
                                 tag="train ", on_step=hook)
        if o.init:
            st["step"] += self.prev[cfg.bits[0]]["steps"]
            st["elapsed"] += self.prev[cfg.bits[0]]["train_elapsed_s"]
        self.st, self.encs, self.decs = st, st["encoders"], st["decoders"]
        if o.half:
            for e in self.encs:
                to_half(e)
        self.log(f"trained {st['step']} steps in {st['elapsed']:.0f} s ({st['steps_per_s']:.2f} steps/s)")

    def whiten(self) -> None:
        """Fit (or take the shipped) whitening of every decoder; the fine-tune targets follow ``ft_target``."""
        o = self.opts
        torch.backends.cudnn.benchmark = False  # evaluation sees many image sizes
        torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False  # whitening in float32
        if o.shipped_whitening:
            whitens, self.nfit = [shipped_whitening(d, k) for d, k in zip(self.decs, self.cfg.bits)], 0
            self.log("whitening: the shipped one")
        else:
            whitens, self.nfit = fit_whitening_multi(self.decs, self.train_images, self.bank,
                                                     num_crops=o.whiten_crops, mode=o.whiten_mode,
                                                     center=o.whiten_center, eps=o.whiten_eps)
            self.log(f"whitening fitted on {self.nfit} samples")
        self.whitens = [w.to(self.device) for w in whitens]
        self.targets = (self.whitens if o.ft_target == "whitened"
                        else [WhiteningLayer(k).to(self.device) for k in self.cfg.bits])

    def init_metas(self) -> None:
        """The run metadata of every bit length (``k{bits}.json``)."""
        o, st, dev = self.opts, self.st, self.device
        dev_name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else (platform.processor() or "cpu")
        self.metas = {k: {
            "num_bits": k, "config": config_dict(self.cfg, k, o.ft_s), "args": dataclasses.asdict(o),
            "steps": st["step"], "train_elapsed_s": st["elapsed"], "steps_per_s": st["steps_per_s"],
            "device": dev_name, "torch": torch.__version__, "python": platform.python_version(),
            "num_train_images": len(self.train_images), "num_val_images": len(self.val_images),
            "whitening_fit_samples": self.nfit, "results": {}, "train_log": st["log"], "val_log": st["val"],
            "ft_log": []} for k in self.cfg.bits}

    def save(self, stage: str) -> None:
        """Rewrite the run folder; with ``half`` and a fine-tune only the fine-tuned encoder is kept."""
        for i, k in enumerate(self.cfg.bits):
            self.metas[k]["wall_s"] = time.perf_counter() - self.t0
            encoders = {} if (self.opts.half and self.ft_encs is not None) else {"encoder": self.encs[i]}
            if self.ft_encs is not None:
                encoders["encoder_ft"] = self.ft_encs[i]
            write_stage(self.out, stage, k, self.metas[k], self.decs[i], self.whitens[i], self.st["step"],
                        encoders, self.opts.half)

    def scaled(self, encoder: torch.nn.Module) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """(imgs, msgs) -> watermarked imgs: ``encoder``'s residual at the target PSNR."""
        cfg = self.cfg
        return lambda x, m: embed_scaled(encoder, x, m, cfg.psnr_target, cfg.enc_down)

    def evaluate(self, i: int, embed: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                 decode: Callable[[torch.Tensor], torch.Tensor], attacks: dict[str, Any],
                 share: float) -> dict[str, Any]:
        """Bit length ``i``: ``embed`` read by ``decode`` on the evaluation photos under ``attacks``, within
        ``share`` of the time left."""
        t_end = time.perf_counter() + max(0.0, self.left()) * share
        return eval_attacks_chunked(embed, decode, self.val_images[: self.opts.eval_images], attacks,
                                    self.cfg.bits[i], self.opts.msgs_per_image, seed=1, device=self.device,
                                    t_end=t_end)

    def _whitened(self, i: int, targets: list[WhiteningLayer]) -> Callable[[torch.Tensor], torch.Tensor]:
        """LL2 -> logits of decoder ``i`` followed by ``targets[i]``."""
        return lambda ll: targets[i](self.decs[i](ll).float())

    def eval_initial(self) -> None:
        """The jointly trained pairs under every attack, then unbiasedness of the decoders."""
        o, bits = self.opts, self.cfg.bits
        for i, k in enumerate(bits):
            r = self.evaluate(i, self.scaled(self.encs[i]), self.decs[i], self.attacks, 0.45 / (len(bits) - i))
            self.metas[k]["results"]["pair_raw"] = r
            self.log(f"k={k} pair_raw ({r['n']} pairs, PSNR {r['psnr']:.1f}): "
                     + " ".join(f"{a}={v:.4f}" for a, v in r["bit_acc"].items()))
        self.save("evaluated_raw")
        for i, k in enumerate(bits):
            res = self.metas[k]["results"]
            u = unbiasedness(self._whitened(i, self.whitens), self.val_images, k, o.num_messages, seed=2,
                             device=self.device, extra_views=10)
            res["unbiased_whitened"] = u
            res["unbiased_raw"] = unbiasedness(self.decs[i], self.val_images, k, o.num_messages, seed=2,
                                               device=self.device)
            res["pair_whitened_before_ft"] = self.evaluate(
                i, self.scaled(self.encs[i]), self._whitened(i, self.whitens), {"identity": self.attacks["identity"]},
                0.05)
            self.log(f"k={k} unbiased: acc={u['mean_bit_acc']:.4f} p1dev={u['per_bit_p1_max_dev']:.3f} "
                     f"views_p1dev={u.get('views_per_bit_p1_max_dev'):.3f} fp={u['false_positives']} "
                     f"max={u['max_matching_bits']} before-ft whitened acc="
                     f"{res['pair_whitened_before_ft']['bit_acc']['identity']:.4f}")
        self.save("evaluated_unbiased")

    def finetune(self) -> None:
        """Fine-tune copies of the encoders against the frozen decoders (``ft_target``), then evaluate them."""
        o, cfg = self.opts, self.cfg
        ft_s = min(o.ft_s, max(0.0, self.left() * 0.4))
        if ft_s < 3:
            return
        warp = cfg.view_warp if o.ft_warp == "same" else o.ft_warp == "on"
        fcfg = dataclasses.replace(cfg, time_budget_s=ft_s, lr=o.ft_lr, view_warp=warp,
                                   clean_chunk=o.ft_clean_chunk, log_every=max(10, o.log_every // 4))
        torch.backends.cudnn.benchmark = self.device.type == "cuda"
        bar, hook = _bar_hook(fcfg, "ft", self.progress, self.log)
        with bar:
            ft = train_multi(fcfg, self.bank, encoders=[copy.deepcopy(e) for e in self.encs], decoders=self.decs,
                             whitenings=self.targets, finetune_encoders=True, tag="ft ", verbose=False,
                             on_step=hook)
        torch.backends.cudnn.benchmark = False
        self.ft_encs = ft["encoders"]
        self.log(f"encoder fine-tune: {ft['step']} steps in {ft['elapsed']:.0f} s")
        if o.half:  # what is evaluated below is exactly what the run file holds
            for e in self.ft_encs:
                to_half(e)
        for k in cfg.bits:
            meta = self.metas[k]
            meta.update(ft_log=ft["log"], ft_steps=ft["step"])
            meta["config"]["ft_s"] = round(ft["elapsed"], 1)
            meta["config"].update(ft_lr=o.ft_lr, ft_view_warp=warp, ft_target=o.ft_target,
                                  ft_clean_chunk=o.ft_clean_chunk)
            if o.init_encoder == "encoder_ft" and not self.trained:  # chained fine-tunes: count the earlier ones
                before = self.prev[k]
                meta["ft_steps_total"] = ft["step"] + before.get("ft_steps_total", before.get("ft_steps", 0))
                meta["ft_s_total"] = round(ft["elapsed"] + before.get(
                    "ft_s_total", before["config"].get("ft_s", 0) if "ft_steps" in before else 0), 1)
        self.save("finetuned")
        for i, k in enumerate(cfg.bits):
            r = self.evaluate(i, self.scaled(self.ft_encs[i]), self._whitened(i, self.targets), self.attacks,
                              0.8 / (len(cfg.bits) - i))
            self.metas[k]["results"][f"pair_{o.ft_target}_ft"] = r
            self.log(f"k={k} pair_{o.ft_target}_ft ({r['n']} pairs): "
                     + " ".join(f"{a}={v:.4f}" for a, v in r["bit_acc"].items()))

    def refined_embedder(self, i: int, steps: int) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """(imgs, msgs) -> watermarked imgs: the last encoder's residual refined against the decoder (+ target)."""
        from gsw.mark.refine import attack_cycle, refine_residual  # noqa: PLC0415  (loads gsw.mark)

        o, cfg = self.opts, self.cfg
        encoder = (self.ft_encs or self.encs)[i]
        attack = (attack_cycle(GpuAttacks(self.device, 11).apply, cfg.noise_layers, o.refine_eot_every)
                  if o.refine_eot else None)
        decode = self._whitened(i, self.targets)

        def embed(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
            return refine_residual(decode, x, encoder_residual(encoder, x, m, cfg.enc_down), m, cfg.psnr_target,
                                   steps, o.refine_lr, o.refine_margin, attack,
                                   amp=self.device.type == "cuda" and not o.refine_fp32, schedule=o.refine_schedule)

        return embed

    def refine(self) -> None:
        """Evaluate the last encoders with their residuals refined for each of ``refine_steps``."""
        o, bits = self.opts, self.cfg.bits
        tuned = self.ft_encs is not None or (o.init_encoder == "encoder_ft" and not self.trained)
        if self.ft_encs is None and tuned:  # no new fine-tune of the init's fine-tuned encoder: its counts stand
            for k in bits:
                self.metas[k].update({n: self.prev[k][n] for n in ("ft_steps", "ft_steps_total", "ft_s_total")
                                      if n in self.prev[k]})
        for steps in o.refine_steps:
            for i, k in enumerate(bits):
                r = self.evaluate(i, self.refined_embedder(i, steps), self._whitened(i, self.targets),
                                  self.attacks, 0.8 / (len(bits) - i))
                r["refine"] = {"steps": steps, "lr": o.refine_lr, "margin": o.refine_margin, "eot": o.refine_eot,
                               "eot_every": o.refine_eot_every, "schedule": o.refine_schedule,
                               "bf16": self.device.type == "cuda" and not o.refine_fp32}
                name = f"pair_{o.ft_target}{'_ft' if tuned else ''}_refine{steps}"
                self.metas[k]["results"][name] = r
                self.log(f"k={k} {name} ({r['n']} pairs, PSNR {r['psnr']:.1f}): "
                         + " ".join(f"{a}={v:.4f}" for a, v in r["bit_acc"].items()))
            self.save("refined")

    def summary(self) -> dict[str, Any]:
        """Steps, time and each evaluation's clean bit accuracy (or unmarked mean accuracy) per bit length."""
        def brief(r: dict[str, Any]) -> float:
            return round(r["bit_acc"]["identity"] if "bit_acc" in r else r["mean_bit_acc"], 4)

        return {"output": str(self.out), "device": str(self.device), "steps": self.st["step"],
                "train_elapsed_s": round(self.st["elapsed"], 1),
                "results": {str(k): {n: brief(r) for n, r in m["results"].items()} for k, m in self.metas.items()}}


def pretrain(opts: PretrainOptions, progress: bool = True) -> dict[str, Any]:
    """Run the whole pre-training (module docstring) into the run folder ``opts.output``.

    The folder is created if needed and its run files are replaced; the caller decides whether an existing
    folder may be written to. Messages go to stderr, with a progress bar over each training phase when
    ``progress``. The TF32 / cuDNN benchmark settings of torch are restored on return.

    Returns:
        a summary: ``output``, ``device``, ``steps``, ``train_elapsed_s`` and ``results`` (per bit length,
        each evaluation's clean bit accuracy, or the unmarked mean bit accuracy).

    Raises:
        ValueError: inconsistent options, or an ``init`` run that does not fit them.
        FileNotFoundError: missing photos or ``init`` run files.
    """
    opts.validate()
    flags = (torch.backends.cudnn.benchmark, torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32)
    run = _Pretraining(opts, progress)
    try:
        run.load_data()
        run.train()
        run.whiten()
        run.init_metas()
        run.save("whitened")
        if not opts.skip_init_eval:  # a chained fine-tune: the init run's numbers stand
            run.eval_initial()
        run.finetune()
        run.refine()
        run.save("done")
        run.log("done")
    finally:
        torch.backends.cudnn.benchmark, torch.backends.cudnn.allow_tf32 = flags[:2]
        torch.backends.cuda.matmul.allow_tf32 = flags[2]
    return run.summary()
