"""``gsw decoder train|export``: pre-train the watermark decoders and export them with their report.

Hook into the main CLI with ``register(subparsers)`` (sets ``func`` on each sub-command). Nothing here loads
the compiled rasterizer: the decoder commands run wherever torch does.

Examples::

    gsw decoder train --data ../shared/data/bsds500 --output runs/dec --bits 32 48 64 --time-budget-s 330
    gsw decoder export runs/dec --data ../shared/data/bsds500 --report benchmarks/results/decoder --force
    gsw decoder export --shipped --data ../shared/data/bsds500 --report benchmarks/results/decoder --force
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

from gsw.cli.common import positive_int

__all__ = ["register", "run_export", "run_train"]


def _add_options(group: argparse._ArgumentGroup, defaults: Any, specs: list[tuple[str, Any, str]]) -> None:
    """``--field-name`` options whose destination and default are the ``PretrainOptions`` field of that name;
    a ``bool`` type makes a flag."""
    for flag, kind, text in specs:
        default = getattr(defaults, flag[2:].replace("-", "_"))
        if kind is bool:
            group.add_argument(flag, action="store_true", help=text)
        elif isinstance(kind, tuple):
            group.add_argument(flag, choices=kind, default=default, help=f"{text} (default %(default)s)")
        else:
            group.add_argument(flag, type=kind, default=default, help=f"{text} (default %(default)s)")


def _add_train_model_options(p: argparse.ArgumentParser, d: Any) -> None:
    """Options of the networks and of the joint training (defaults from ``d``, a ``PretrainOptions``)."""
    _add_options(p.add_argument_group("networks"), d, [
        ("--channels", positive_int, "network width (64 ships; small widths for tests)"),
        ("--enc-blocks", positive_int, "encoder Conv-BN blocks"),
        ("--dec-blocks", positive_int, "decoder Conv-BN blocks"),
        ("--dec-norm", ("none", "center", "standardize"), "decoder input normalisation"),
        ("--enc-down", positive_int, "encoder resolution divisor (training aid)"),
        ("--templates", int, "> 0: on/off template encoder aid of this side"),
        ("--template-mlp", int, "> 0: nonlinear message -> template branch of this width"),
        ("--template-refine", int, "> 0: image-adaptive refiner of the template of this width")])
    _add_options(p.add_argument_group("joint training"), d, [
        ("--batch", positive_int, "crops per step and bit length"),
        ("--crop", positive_int, "crop side"),
        ("--lr", float, "AdamW learning rate (warmup + cosine)"),
        ("--psnr", float, "PSNR of the watermark at the end of the curriculum"),
        ("--psnr-start", float, "PSNR of the watermark while learning the code"),
        ("--clean-frac", float, "fraction of the run without attacks"),
        ("--noise-ramp-end", float, "attack strength reaches 1 at this fraction"),
        ("--clean-chunk", bool, "half of every batch is never attacked"),
        ("--view-warp", bool, "every sample also goes through a random view warp"),
        ("--balance", float, "weight of the unmarked-balance loss"),
        ("--balance-batch", positive_int, "unmarked crops per step for that loss"),
        ("--freeze-bn", bool, "decoder BatchNorm in eval mode (fine-tuning)"),
        ("--amp", ("auto", "on", "off"), "bf16 autocast (auto: on CUDA)"),
        ("--init", str, "continue from this earlier run folder (with --steps 0: no further training)"),
        ("--init-encoder", ("encoder", "encoder_ft"), "which encoder of --init to start from"),
        ("--log-every", positive_int, "steps between log lines"),
        ("--val-every-s", float, "seconds between validations")])


def _add_train_eval_options(p: argparse.ArgumentParser, d: Any) -> None:
    """Options of the whitening, the encoder fine-tune, the evaluation and the run files."""
    _add_options(p.add_argument_group("whitening"), d, [
        ("--shipped-whitening", bool, "use the package's whitening (the decoders must be the shipped ones)"),
        ("--whiten-mode", ("pca", "zca"), "whitening"),
        ("--whiten-center", ("mean", "median"), "whitening centre"),
        ("--whiten-eps", float, "eigenvalue floor relative to the largest"),
        ("--whiten-crops", int, "random unmarked crops in the fit")])
    _add_options(p.add_argument_group("encoder fine-tune against the frozen decoders"), d, [
        ("--ft-s", float, "seconds (< 3: none)"),
        ("--ft-lr", float, "learning rate (cosine)"),
        ("--ft-warp", ("same", "on", "off"), "view warp (same: as in training)"),
        ("--ft-target", ("whitened", "raw"), "decoder output fine-tuned against (and evaluated with)"),
        ("--ft-clean-chunk", bool, "half of every batch is never attacked")])
    g = p.add_argument_group("evaluation (DATA/val photos at full size)")
    _add_options(g, d, [
        ("--eval-images", positive_int, "photos in the attack evaluation"),
        ("--msgs-per-image", positive_int, "messages per photo there"),
        ("--num-messages", positive_int, "random messages against the unmarked photos"),
        ("--limit-images", positive_int, "read only the first N train and val photos"),
        ("--skip-init-eval", bool, "skip the evaluation before the fine-tune (chained fine-tunes)")])
    g.add_argument("--refine-steps", type=int, nargs="*", default=[],
                   help="also evaluate the last encoders with their residual refined this many Adam steps against "
                        "the decoder (needs the full gsw package); one evaluation each")
    _add_options(g, d, [
        ("--refine-lr", float, "learning rate of that refinement"),
        ("--refine-schedule", ("cosine", "constant"), "its schedule"),
        ("--refine-margin", float, "its logit margin"),
        ("--refine-eot", bool, "refine through the training noise layers too (in turn)"),
        ("--refine-eot-every", positive_int, "with --refine-eot, attack every n-th step only"),
        ("--refine-fp32", bool, "refine in float32 (default on CUDA: bf16)")])
    _add_options(p.add_argument_group("output"), d, [
        ("--half", bool, "float16 encoders in the run files (only the last one kept)"),
        ("--deadline-s", float, "end every stage by then (seconds from the start)")])


def _add_train_parser(sub: argparse._SubParsersAction) -> None:
    """``gsw decoder train``."""
    from gsw.decoder.pretrain.pipeline import PretrainOptions  # noqa: PLC0415

    d = PretrainOptions(data="", output="")
    p = sub.add_parser(
        "train", help="pre-train, whiten and evaluate the watermark decoders (a run folder)",
        description="Pre-train one HiDDeN encoder/decoder pair per bit length on crops of DATA/train (device-side "
                    "attacks, curriculum), whiten the decoders, evaluate them on DATA/val, fine-tune the encoders "
                    "against the frozen decoders; writes k{bits}.pt/.json into the run folder after every stage. "
                    "`gsw decoder export RUN` then installs the decoders.")
    p.add_argument("--data", required=True, help="photo folder with train/ and val/ (e.g. ../shared/data/bsds500)")
    p.add_argument("--output", required=True, help="the run folder to write (a new or empty folder)")
    p.add_argument("--force", action="store_true", help="write into an existing non-empty run folder")
    p.add_argument("--bits", type=positive_int, nargs="+", default=list(d.bits), help="bit lengths (default 32 48 64)")
    p.add_argument("--steps", type=int, default=d.steps, help="training steps (default %(default)s)")
    p.add_argument("--time-budget-s", type=float, default=None,
                   help="training wall time for all bit lengths instead of --steps")
    p.add_argument("--device", default="auto", help="auto (CUDA when available), cpu, cuda or cuda:N")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--no-progress", action="store_true", help="log lines instead of a progress bar")
    _add_train_model_options(p, d)
    _add_train_eval_options(p, d)
    p.set_defaults(func=run_train)


def _add_export_parser(sub: argparse._SubParsersAction) -> None:
    """``gsw decoder export``."""
    p = sub.add_parser(
        "export", help="install decoders (weights + manifest) and write their report",
        description="Save the decoders of a run folder (or re-save the shipped ones, --shipped) as "
                    "hidden_k{bits}.pt with a manifest.json, re-measure them on the CPU on DATA/val and write the "
                    "report STEM.json / STEM.md. Existing weights or reports are replaced only with --force.")
    p.add_argument("run", nargs="?", help="run folder of `gsw decoder train` (not with --shipped)")
    p.add_argument("--shipped", action="store_true",
                   help="re-save the package's decoders and re-measure them; the training records come from "
                        "--previous-report")
    p.add_argument("--data", required=True, help="photo folder with train/ and val/")
    p.add_argument("--report", required=True, help="report path without suffix (writes REPORT.json and REPORT.md)")
    p.add_argument("--weights-dir", default=None, help="where the weights and manifest go (default: the package's)")
    p.add_argument("--previous-report", default=None,
                   help="earlier report JSON: its other bit lengths (run) or its training records (--shipped) are "
                        "kept (default: REPORT.json when it exists)")
    p.add_argument("--bits", type=positive_int, nargs="+", default=[32, 48, 64], help="bit lengths (default 32 48 64)")
    p.add_argument("--force", action="store_true", help="replace existing weights, manifest or report")
    p.add_argument("--refit-whitening", action="store_true", help="refit the whitening here on the CPU (run only)")
    p.add_argument("--whiten-crops", type=int, default=1600, help="random crops in that refit (default %(default)s)")
    p.add_argument("--whiten-eps", type=float, default=1e-3, help="its eigenvalue floor (default %(default)s)")
    p.add_argument("--ft-runs", nargs="*", default=[], help="encoder fine-tune runs of these decoders to merge in")
    p.add_argument("--recheck-bits", type=positive_int, nargs="*", default=[],
                   help="re-measure a fine-tuned pair on the CPU for these bit lengths (95 %% photo bootstrap)")
    p.add_argument("--recheck-run", default=None, help="the run whose encoder_ft is re-checked (default: last --ft-runs)")
    p.set_defaults(func=run_export)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``gsw decoder {train,export}`` to the ``gsw`` sub-commands."""
    p = subparsers.add_parser("decoder", help="pre-train and export the watermark decoders",
                              description="Pre-training of the watermark decoders: `train` writes a run folder, "
                                          "`export` installs its decoders and writes the report.")
    sub = p.add_subparsers(dest="decoder_command", required=True)
    _add_train_parser(sub)
    _add_export_parser(sub)


def _device(name: str) -> str:
    """``auto`` -> ``cuda`` when torch sees a GPU, else ``cpu``; a CUDA device torch cannot use is an error."""
    import torch  # noqa: PLC0415

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name != "cpu" and not (name == "cuda" or name.startswith("cuda:")):
        raise ValueError(f"--device must be auto, cpu, cuda or cuda:N, got {name!r}")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError(f"--device {name}: no CUDA device is available to torch")
    return name


def _check_new_output(path: Path, force: bool, what: str) -> None:
    """Refuse a non-empty existing folder (or a file) at ``path`` unless ``force``."""
    if path.exists() and not path.is_dir():
        raise ValueError(f"{what} {path} exists and is not a folder")
    if path.is_dir() and any(path.iterdir()) and not force:
        raise ValueError(f"{what} {path} exists and is not empty (pass --force to write into it)")


def run_train(args: argparse.Namespace) -> int:
    """``gsw decoder train``: prints the run summary as JSON; returns the exit status."""
    from gsw.decoder.pretrain.pipeline import PretrainOptions, pretrain  # noqa: PLC0415

    _check_new_output(Path(args.output), args.force, "run folder")
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(PretrainOptions)}
    values.update(bits=tuple(args.bits), refine_steps=tuple(args.refine_steps), device=_device(args.device))
    opts = PretrainOptions(**values)
    summary = pretrain(opts, progress=not args.no_progress)
    print(json.dumps(summary))
    return 0


def _log(msg: str) -> None:
    """A progress line of ``gsw decoder export`` on stderr."""
    print(f"gsw decoder export: {msg}", file=sys.stderr, flush=True)


def _export_targets(args: argparse.Namespace) -> tuple[Path, Path | None]:
    """The weights folder and the previous report (None: none), after the --force checks."""
    from gsw.cli.common import check_output, input_paths  # noqa: PLC0415
    from gsw.decoder.zoo import MANIFEST, WEIGHTS_DIR, weights_path  # noqa: PLC0415

    if args.shipped == (args.run is not None):
        raise ValueError("give either a run folder or --shipped")
    if args.shipped and args.refit_whitening:
        raise ValueError("--refit-whitening refits a run's whitening; the shipped whitening is re-saved as it is")
    if args.recheck_bits and not (args.recheck_run or args.ft_runs):
        raise ValueError("--recheck-bits needs --recheck-run or --ft-runs")
    wdir = Path(args.weights_dir) if args.weights_dir else WEIGHTS_DIR
    stem = Path(args.report)
    targets = [weights_path(k, wdir) for k in args.bits] + [wdir / MANIFEST]
    targets += [stem.parent / (stem.name + ext) for ext in (".json", ".md")]
    inputs = input_paths(args, "data", "run", "recheck_run") + [Path(r) for r in args.ft_runs or []]
    for target in targets:  # the report and weights never overwrite a training run or the photos
        check_output(target, inputs, force=True)
    existing = [str(t) for t in targets if t.exists()]
    if existing and not args.force:
        raise ValueError(f"{', '.join(existing)} exist (pass --force to replace them; the shipped weights are "
                         "never replaced without it)")
    previous = Path(args.previous_report) if args.previous_report else stem.parent / (stem.name + ".json")
    if not previous.is_file():
        if args.previous_report or args.shipped:
            raise FileNotFoundError(f"previous report not found: {previous}" + (
                " (--shipped takes the training records from it)" if args.shipped else ""))
        previous = None
    wdir.mkdir(parents=True, exist_ok=True)
    return wdir, previous


def _read_report(path: Path) -> dict[str, Any]:
    """A decoder report JSON, with an error naming the file when it is not one."""
    try:
        rep = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not valid JSON: {e}") from e
    if not isinstance(rep, dict) or not isinstance(rep.get("runs"), dict):
        raise ValueError(f"{path} is not a decoder report (no 'runs' object)")
    return rep


def run_export(args: argparse.Namespace) -> int:
    """``gsw decoder export``: prints what it wrote as JSON; returns the exit status."""
    from gsw.decoder.pretrain import export as X  # noqa: PLC0415
    from gsw.decoder.pretrain.data import load_split  # noqa: PLC0415

    wdir, prev_path = _export_targets(args)
    previous = _read_report(prev_path) if prev_path else None
    bits = tuple(args.bits)
    changes: list[str] = []
    if args.shipped:
        rep, changes = X.export_shipped(previous, args.data, wdir, bits, log=_log)
        for line in changes:
            _log(f"changed: {line}")
    else:
        rep = X.export_run(args.run, args.data, wdir, bits, previous, args.refit_whitening, args.whiten_crops,
                           args.whiten_eps, log=_log)
    if args.ft_runs:
        X.merge_ft_runs(rep, args.ft_runs, bits)
    if args.recheck_bits:
        val_images = load_split(args.data, "val")
        for k in args.recheck_bits:
            _log(f"{k} bits: CPU re-check of the fine-tuned pair")
            rep["runs"][str(k)]["results"]["pair_ft_cpu_recheck"] = X.cpu_pair_recheck(
                args.recheck_run or args.ft_runs[-1], k, val_images, weights_dir=wdir)
    js, md = X.write_report(rep, args.report)
    print(json.dumps({"weights_dir": str(wdir), "bits": list(bits), "report": [str(js), str(md)],
                      "changed": changes}))
    return 0
