"""`gsw fingerprint` (one watermarked copy per recipient, registered) and `gsw scan` (who leaked these?).

`gsw fingerprint` runs its recipient batches on Ray when it is installed (a local Ray cluster, or ``--address``
to join one) and in one process otherwise. `gsw scan` runs in one process unless ``--address``, ``--workers`` or
several visible GPUs (with ``--device cuda``) call for Ray Data (:func:`gsw.fingerprint.scan.ray_by_default`).
Messages are secrets: they go into the registry only, never into the output folders or the printed report.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
import time
from pathlib import Path

from gsw.cli.common import (REGISTRY_HELP, add_background_options, add_bits_option, add_device_option,
                            add_mse_option, add_readout_option, add_resize_images_option, check_readout_origin,
                            positive_int, print_json, readout_decoder, reading)
from gsw.fingerprint.batched import POOL_LPIPS
from gsw.fingerprint.scan import DEFAULT_BATCH_SIZES, DEFAULT_READERS
from gsw.stats import DETECTION_FPR

__all__ = ["register", "cmd_fingerprint", "cmd_scan"]



def register(subparsers: argparse._SubParsersAction) -> None:
    """Adds ``fingerprint`` and ``scan``."""
    fp = subparsers.add_parser("fingerprint", help="one watermarked copy per recipient, each registered",
                               description="Writes OUTPUT/<recipient>/ (an INRIA model folder) for every recipient of "
                               "the recipients CSV (header: recipient[,message][,key]) and registers its secret "
                               "message. A rerun skips finished recipients.")
    fp.add_argument("input", help="INRIA model folder, or a .ply/.splat with --cameras")
    fp.add_argument("--cameras", help="INRIA cameras.json (with a .ply/.splat input)")
    fp.add_argument("--images", help="folder of the training images (optional, for FGD)")
    add_resize_images_option(fp)
    fp.add_argument("--recipients", required=True, help="recipients CSV file")
    fp.add_argument("--output", required=True, help="the job's folder (new, or this scene's earlier job)")
    fp.add_argument("--registry", help=REGISTRY_HELP)
    add_bits_option(fp, 32, "message length (default: %(default)s)")
    fp.add_argument("--batch", type=positive_int, default=4,
                    help="recipients fine-tuned together: the slots of the pool (default %(default)s)")
    fp.add_argument("--early-stop", nargs="?", const="quality", default="quality", metavar="SETTINGS",
                    help="finish each recipient once its own training renders decode right (and refill its slot), "
                         "its message weight steered to psnr_target if set (gsw.fingerprint.stopping.EarlyStop): a "
                         "preset "
                         "(quality, careful, focused, assured, probed, throughput: gsw.fingerprint.stopping.PRESETS) "
                         "and/or 'min_steps=N,window=N,margin=X,check_every=N,psnr_target=DB,adapt=X,confirm=ACC,"
                         "extend=F,accuracy_window=N,redraw=N,redraw_bits=ACC,focus=P,probes=N,probe_bits=ACC', e.g. "
                         "'quality,extend=1'; 'none': every recipient runs --epochs passes. Default (also of a bare "
                         "--early-stop) %(default)s: on lego 800x800 with the pool's default recipe 32 of 32 copies "
                         "met >= 99 %% bits and >= 37 dB held-out at 1,564 per GPU-hour with --batch 16 (README, "
                         "BENCHMARKS.md)")
    fp.add_argument("--task-size", type=positive_int, default=None,
                    help="recipients handed to a Ray worker at a time (default: --batch)")
    fp.add_argument("--epochs", type=positive_int, default=8)
    fp.add_argument("--freeze", type=_groups, default=None, metavar="GROUPS",
                    help="parameter groups kept fixed, comma-separated (f_dc, f_rest, opacity, scaling, rotation), "
                         "or 'none' (the paper's recipe, with --mask exp); default f_rest: the mark then survives "
                         "SH-degree-0 viewers and .splat / .spz exports")
    fp.add_argument("--mask", choices=["exp", "stega", "none"], default=None,
                    help="gradient mask (default none; the paper's: exp)")
    fp.add_argument("--lpips", choices=["vgg", "alex", "none"], default=POOL_LPIPS,
                    help="LPIPS network of the loss (default %(default)s: the pool's measured setting)")
    fp.add_argument("--fgd", action=argparse.BooleanOptionalAction, default=None,
                    help="frequency-guided densification, once for the scene (default: off, as gsw embed's "
                         "default recipe; the paper's recipe: on)")
    fp.add_argument("--attacks", type=float, default=0.0, help="train-time image-attack probability")
    fp.add_argument("--novel-views", type=float, default=0.0, metavar="P",
                    help="share of the steps rendered from a viewpoint sampled around the content instead of a "
                         "camera (default %(default)s; 0.5 on a lego model: held-out bits of the worst copy "
                         "98.6 %% instead of 93.5 %%, PSNR 37.4 instead of 37.9 dB, a third fewer copies per hour; "
                         "BENCHMARKS.md, twelfth GPU round)")
    fp.add_argument("--view-bank", type=int, default=0, metavar="B",
                    help="with --novel-views: sample B viewpoints once per job and draw the steps' viewpoints from "
                         "them, their original renders and loss references made once (default %(default)s: a fresh "
                         "viewpoint per step)")
    fp.add_argument("--message-weight", type=float, default=None, help="weight of the message loss")
    add_mse_option(fp)
    add_background_options(fp, "default: black")
    add_readout_option(fp)
    fp.add_argument("--seed", type=int, default=0, help="view order seed (messages are drawn from os.urandom)")
    add_device_option(fp)
    _add_ray_options(fp)
    fp.add_argument("--gpus-per-task", type=float, default=1.0,
                    help="GPUs per Ray worker (default %(default)s: one worker per GPU)")
    fp.add_argument("--max-retries", type=int, default=3,
                    help="reruns of a batch whose Ray worker dies (and restarts of a worker)")
    fp.add_argument("--no-progress", action="store_true")
    fp.add_argument("--json", action="store_true", help="print the report as JSON")
    fp.set_defaults(func=cmd_fingerprint, model_attack_prob=0.0, psnr_target=None)  # the pool has neither

    sc = subparsers.add_parser("scan", help="test many images and videos against every registered mark",
                               description="Each image, and each video (its frames together), is tested against every "
                               "registered mark (gsw identify); a report of detections with calibrated p-values.")
    sc.add_argument("inputs", nargs="+", metavar="DIR|GLOB|FILE", help="folders (recursive), glob patterns, image or "
                    "video files")
    sc.add_argument("--registry", help=REGISTRY_HELP)
    sc.add_argument("--output", help="report file: .csv or .json (default: a table on stdout)")
    sc.add_argument("--fpr", type=float, default=DETECTION_FPR, help="family-wise false-positive rate per source")
    sc.add_argument("--frames", type=positive_int, default=16, help="frames read per video (default %(default)s)")
    add_device_option(sc)
    _add_ray_options(sc)
    sc.add_argument("--workers", type=positive_int, default=None,
                    help="scan on this many Ray Data workers (a local Ray cluster unless --address; default: Ray Data "
                         "only on several GPUs or a cluster, one worker per GPU/CPU)")
    sc.add_argument("--batch-size", type=positive_int, default=None,
                    help="images per decoder call (default: " + ", ".join(f"{n} on {d}" for d, n in
                                                                      DEFAULT_BATCH_SIZES.items()) + ")")
    sc.add_argument("--readers", type=positive_int, default=DEFAULT_READERS,
                    help="threads reading images and videos, per process (default %(default)s)")
    sc.add_argument("--no-progress", action="store_true",
                    help="no progress bar (on Ray it advances as each worker call returns)")
    sc.set_defaults(func=cmd_scan)


def _groups(text: str) -> tuple[str, ...]:
    """``--freeze``: parameter group names (``none``: no group), checked as the embedding checks them."""
    from gsw.mark.embed import check_freeze

    names = () if text == "none" else tuple(n.strip() for n in text.split(",") if n.strip())
    if not names and text != "none":
        raise argparse.ArgumentTypeError(f"--freeze takes 'none' or parameter group names, got {text!r}")
    try:
        check_freeze(names)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return names


def _add_ray_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--address", help="Ray cluster to join (default: a local Ray cluster when Ray is installed)")
    group.add_argument("--local", action="store_true", help="run in this process even when Ray is installed")


def _use_ray(args: argparse.Namespace) -> bool | None:
    """False for ``--local``; True for ``--address`` or (scan) ``--workers``; None: the library's default."""
    if args.local:
        return False
    return True if args.address or getattr(args, "workers", None) else None


def cmd_fingerprint(args: argparse.Namespace) -> int:
    """Fingerprints a model for every recipient; exit 0 when every copy is written and registered."""
    from gsw.cli.mark import _load_model, embed_config
    from gsw.device import resolve_device
    from gsw.fingerprint import fingerprint, read_recipients
    from gsw.fingerprint.batched import pool_config
    from gsw.fingerprint.stopping import EarlyStop

    with reading(args.recipients):
        recipients = read_recipients(args.recipients, args.bits)  # bad input fails before the model is loaded
    early_stop = None if args.early_stop == "none" else EarlyStop.parse(args.early_stop)
    redraws = early_stop is not None and early_stop.redraw > 0  # a redrawn message is registered as chosen
    check_readout_origin(args.readout, "chosen" if redraws or any(r.message is not None for r in recipients)
                         else "random", args.bits)
    device = resolve_device(args.device)
    t0 = time.perf_counter()
    g, cams, images = _load_model(args)
    load_s = time.perf_counter() - t0
    if cams is None:
        raise ValueError(f"{args.input} is a bare model: gsw fingerprint needs its cameras (--cameras cameras.json, "
                         "or an INRIA model folder)")
    report = fingerprint(g, cams, recipients, args.output, args.registry, num_bits=args.bits,
                         decoder=readout_decoder(args.readout, args.bits),
                         config=embed_config(args, pool_config()), images=None if images is None else list(images),
                         batch_size=args.batch, early_stop=early_stop, task_size=args.task_size, device=device,
                         use_ray=_use_ray(args), address=args.address, gpus_per_task=args.gpus_per_task,
                         max_retries=args.max_retries,
                         progress=not args.no_progress)
    report.timings["load"] = load_s  # the model folder and its images, before the job
    if args.json:
        print_json(report.to_dict())
        return 0
    for r in report.recipients:
        if r.status == "embedded":
            print(f"embedded {r.name}: {100 * r.bit_accuracy:.2f} % of the bits (worst view "
                  f"{100 * r.min_bit_accuracy:.1f} %), {r.psnr:.2f} dB, {r.steps} steps -> {r.folder}")
        else:
            print(f"{r.status} {r.name} (finished earlier) -> {r.folder}")
    how = "nothing to run" if report.runner == "none" else f"{report.runner} runner"
    print(f"{len(report.names('embedded'))} embedded, {len(report.recipients) - len(report.names('embedded'))} "
          f"already done ({how}, {report.timings.get('total', 0.0):.1f} s); messages are in the registry only")
    redrawn = [r.name for r in report.recipients if r.redraws]
    if redrawn:
        print(f"{len(redrawn)} recipient(s) got a new message after a copy that read too few bits "
              f"({', '.join(redrawn)}): registered as chosen messages (tested with the decoder's calibrated null "
              "model)")
    _warn_unconfirmed(report, early_stop)
    return 0


def _warn_unconfirmed(report, rule) -> None:
    """Names on stderr the copies of this run that finished without passing ``rule``'s confirmation on the
    embedding views (the step cap, and any extension, reached first)."""
    if rule is None:
        return
    weak = [r for r in report.recipients if r.status == "embedded" and not rule.confirmed(r.bit_accuracy, r.psnr)]
    if not weak:
        return
    bar = f">= {100 * rule.confirm:g} % bits" + ("" if rule.psnr_target is None else f", >= {rule.psnr_target:g} dB")
    names = ", ".join(f"{r.name} ({100 * r.bit_accuracy:.2f} %, {r.psnr:.2f} dB)" for r in weak)
    print(f"warning: {len(weak)} of {len(report.names('embedded'))} copies reached the step cap without passing the "
          f"early-stop confirmation on the embedding views ({bar}): {names}. In the lego jobs of BENCHMARKS.md 10 of "
          "30 such copies read below 99 % of their bits or 37 dB on held-out views (3 of 162 confirmed copies did): "
          "check their renders with gsw verify before shipping them.", file=sys.stderr)


def _write_report(rows: list, output: str | None) -> None:
    from gsw._atomic import atomic_write

    dicts = [r.to_dict() for r in rows]
    if output is None:
        for r in rows:
            found = f"IDENTIFIED {r.identified}" if r.identified else ("error: " + r.error if r.error else "nobody")
            best = "" if r.best_adjusted_p is None else f" (best {r.best_label}: adjusted p = {r.best_adjusted_p:.2e})"
            print(f"{r.source}: {found}{best}")
        return
    path = Path(output)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as f:
        if path.suffix.lower() == ".json":
            json.dump(dicts, f, indent=2)
            f.write("\n")
        else:
            buf = io.StringIO()
            writer = csv.DictWriter(buf, fieldnames=list(dicts[0]))
            writer.writeheader()
            writer.writerows(dicts)
            f.write(buf.getvalue())


def cmd_scan(args: argparse.Namespace) -> int:
    """Scans images and videos; exit 0 when some source identifies a recipient, 1 when none does."""
    from gsw.device import resolve_device
    from gsw.fingerprint.scan import scan
    from gsw.registry import open_registry

    if not 0.0 < args.fpr < 1.0:
        raise ValueError(f"--fpr must lie in (0, 1), got {args.fpr}")
    if args.output is not None and Path(args.output).suffix.lower() not in (".csv", ".json"):
        raise ValueError(f"--output {args.output}: the report is .csv or .json")
    with open_registry(args.registry, create=False) as reg:
        marks = reg.list()
    device = resolve_device(args.device)
    rows = scan(args.inputs, marks, fpr=args.fpr, device=None if device.type == "cpu" else device,
                frames=args.frames, use_ray=_use_ray(args), address=args.address, workers=args.workers,
                batch_size=args.batch_size, readers=args.readers, progress=not args.no_progress)
    _write_report(rows, args.output)
    hits = [r for r in rows if r.identified]
    errors = [r for r in rows if r.error]
    print(f"scanned {len(rows)} source(s): {len(hits)} identified, {len(errors)} unreadable", file=sys.stderr)
    return 0 if hits else 1
