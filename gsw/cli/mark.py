"""`gsw embed`, `gsw embed-image`, `gsw extract`, `gsw verify`: putting the watermark in and reading it back."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from gsw.cli.common import (DEFAULT_BITS, READOUTS, add_background_options, add_bits_option, add_device_option,
                            add_message_options, add_mse_option, add_readout_option, add_resize_images_option,
                            background_of, check_output, check_readout_origin, input_paths, message_from_args,
                            not_detectable_warning, output_file, output_folder, positive_float, positive_int,
                            print_json, readout_decoder, reading)
from gsw.cli.registry import add_record_options, check_record, issued_summary, record_issued
from gsw.stats import DETECTION_FPR


def register(subparsers: argparse._SubParsersAction) -> None:
    """Adds ``embed``, ``embed-image``, ``extract`` and ``verify``."""
    _add_embed_parser(subparsers)
    _add_embed_image_parser(subparsers)
    ext = subparsers.add_parser("extract", help="read the message bits of images")
    ext.add_argument("images", nargs="+", metavar="IMAGE|VIDEO|FOLDER",
                     help="image files, video files and folders of them (searched recursively): one line each image "
                          "and video frame")
    add_bits_option(ext, DEFAULT_BITS, "message length (default: %(default)s)")
    ext.add_argument("--embed-size", metavar="WxH", type=_size,
                     help="embedding resolution: read every image resized to it, as verify does")
    add_readout_option(ext)
    ext.add_argument("--json", action="store_true")
    ext.set_defaults(func=cmd_extract)

    ver = subparsers.add_parser("verify", help="test images or a model for a message (exit 0 = detected)")
    ver.add_argument("images", nargs="*", metavar="IMAGE|VIDEO|FOLDER",
                     help="image files, video files and folders of them (searched recursively), taken together")
    ver.add_argument("--model", help="INRIA model folder to render instead of images (its watermark.json gives the "
                                     "bit length, background, resolution and whether the message was chosen)")
    add_message_options(ver, claim=True)
    ver.add_argument("--chosen-message", action="store_true",
                     help="the message was chosen by someone (e.g. embedded with --message HEX), not drawn at random "
                          "by gsw or derived from a key: test it against the decoder's calibrated null model instead "
                          "of the exact test for random messages")
    add_background_options(ver, "default: the model's watermark.json, else black")
    add_readout_option(ver)
    ver.add_argument("--fpr", type=float, default=DETECTION_FPR, help="false-positive rate of the decision")
    add_device_option(ver)
    ver.add_argument("--json", action="store_true")
    ver.set_defaults(func=cmd_verify)


def _add_embed_parser(subparsers: argparse._SubParsersAction) -> None:
    emb = subparsers.add_parser("embed", help="watermark a model, writing a new INRIA model folder")
    emb.add_argument("input", help="INRIA model folder, or a .ply/.splat (views sampled around it without --cameras)")
    emb.add_argument("--cameras", help="INRIA cameras.json (with a .ply/.splat input; optional)")
    emb.add_argument("--images", help="folder of the training images (optional, for FGD)")
    add_resize_images_option(emb)
    emb.add_argument("--output", required=True, help="new model folder (never the input)")
    emb.add_argument("--force", action="store_true", help="replace an existing output folder")
    add_message_options(emb, claim=False)
    emb.add_argument("--recipe", choices=["default", "paper"], default="default",
                     help="default: SH rest kept, no mask, a sampled viewpoint every step (robust to new viewpoints "
                          "and SH-0 / .splat exports); paper: the 3D-GSW paper's recipe (default %(default)s)")
    emb.add_argument("--epochs", type=positive_int, default=8)
    emb.add_argument("--mask", choices=["exp", "stega", "none"], default=None,
                     help="gradient mask (default: the recipe's: none, paper: exp)")
    emb.add_argument("--psnr-target", type=float, default=None, metavar="DB",
                     help="steer the message weight so the fine-tune's renders hold this PSNR against the "
                          "original's (e.g. 37; costs robustness; default: a fixed weight)")
    emb.add_argument("--render-scales", type=positive_float, nargs=2, metavar=("LOW", "HIGH"), default=None,
                     help="render each step's view at a size factor drawn log-uniformly from [LOW, HIGH] so that "
                          "the mark also reads at other sizes (e.g. 0.5 1; with --epochs 32 for a PLY without "
                          "cameras, BENCHMARKS.md 9g; default: the recipe's, 1 1)")
    emb.add_argument("--lpips", choices=["vgg", "alex", "none"], default="vgg")
    emb.add_argument("--fgd", action=argparse.BooleanOptionalAction, default=None,
                     help="frequency-guided densification before the fine-tune (default: the recipe's: off, paper: on)")
    emb.add_argument("--attacks", type=float, default=0.0, help="train-time image-attack probability")
    emb.add_argument("--model-attack-prob", type=float, default=0.0,
                     help="train-time model-attack probability (parameter noise / SH degree 0)")
    emb.add_argument("--message-weight", type=float, default=None,
                     help="weight of the message loss (default: LossWeights.message)")
    add_mse_option(emb)
    add_background_options(emb, "default: black")
    add_readout_option(emb)
    emb.add_argument("--seed", type=int, default=0, help="optimisation seed (never the message)")
    emb.add_argument("--holdout-every", type=int, default=8, metavar="N",
                     help="embed without every N-th camera and verify the output on those (with fewer than N "
                          "cameras, or 0: verify on the embedding cameras; default %(default)s)")
    emb.add_argument("--fpr", type=float, default=DETECTION_FPR,
                     help="false-positive rate of the output check (exit 1 if not detected; default %(default)g)")
    add_record_options(emb)
    add_device_option(emb)
    emb.add_argument("--no-progress", action="store_true")
    emb.add_argument("--json", action="store_true")
    emb.set_defaults(func=cmd_embed)


def _add_embed_image_parser(subparsers: argparse._SubParsersAction) -> None:
    from gsw.mark.image import ImageEmbedConfig

    emi = subparsers.add_parser("embed-image", help="watermark 2-D images (PNG out), readable by extract/verify")
    emi.add_argument("images", nargs="+", help="input images (PNG, JPEG, ...; alpha is composited on black)")
    emi.add_argument("--output", required=True,
                     help="new .png file (one input) or new folder of <name>.png files (several); never an input")
    emi.add_argument("--force", action="store_true", help="replace an existing output")
    emi.add_argument("--batch", type=positive_int, default=8,
                     help="same-size images optimised together (default %(default)s)")
    add_message_options(emi, claim=False)
    add_record_options(emi)
    emi.add_argument("--psnr", type=float, default=ImageEmbedConfig.psnr,
                     help="PSNR of the watermark in dB (higher = fainter and less robust; default %(default)s)")
    emi.add_argument("--steps", type=int, default=ImageEmbedConfig.steps,
                     help="optimisation steps (more = more robust, linear time; default %(default)s)")
    add_readout_option(emi)
    emi.add_argument("--seed", type=int, default=0, help="optimisation seed (never the message)")
    add_device_option(emi)
    emi.add_argument("--no-progress", action="store_true")
    emi.add_argument("--json", action="store_true")
    emi.set_defaults(func=cmd_embed_image)


# ------------------------------------------------------------------------------------------------ embed


def chosen_message_note(args: argparse.Namespace, command: str) -> str:
    """The origin of the message an embedding command issues: ``"chosen"`` for ``--message HEX`` (with a one-line
    note on stderr that its verification must say so), else ``"random"`` (a fresh secret message, or ``--key``)."""
    if args.message is None:
        return "random"
    print(f"gsw {command}: note: --message HEX is a chosen message; verify it with `gsw verify --chosen-message` "
          "(the exact test assumes a random message: omit --message, or use --key)", file=sys.stderr)
    return "chosen"


def embed_config(args: argparse.Namespace, base=None):
    """The :class:`~gsw.mark.embed.EmbedConfig` of `gsw embed`'s (or `gsw fingerprint`'s) options.

    Args:
        args: the parsed options.
        base: the settings the options apply to (default: ``--recipe``'s: ``EmbedConfig()`` or the paper's).
    """
    from gsw.mark.embed import EmbedConfig, paper_config
    from gsw.mark.loss import PAPER_IMAGE_TERM, lpips_weights

    if base is None:
        base = paper_config() if args.recipe == "paper" else EmbedConfig()
    lpips_net = None if args.lpips == "none" else args.lpips
    weights = lpips_weights(lpips_net, base.weights)
    if args.message_weight is not None:
        weights = dataclasses.replace(weights, message=args.message_weight)
    if args.mse is not None:  # 0: the paper's L1 image term
        weights = dataclasses.replace(weights, **(PAPER_IMAGE_TERM if args.mse == 0 else dict(l1=0.0, mse=args.mse)))
    scales = getattr(args, "render_scales", None)  # `gsw fingerprint` has no such option
    novel = getattr(args, "novel_views", None)  # `gsw embed` takes it from --recipe
    bank = getattr(args, "view_bank", None)
    if scales is not None and scales[0] > scales[1]:
        raise ValueError(f"--render-scales LOW HIGH needs LOW <= HIGH, got {scales[0]:g} {scales[1]:g}")
    freeze = getattr(args, "freeze", None)  # `gsw embed` takes it from --recipe
    return dataclasses.replace(base, epochs=args.epochs, fgd=base.fgd if args.fgd is None else args.fgd,
                               mask=args.mask or base.mask, freeze=base.freeze if freeze is None else freeze,
                               render_scales=base.render_scales if scales is None else tuple(scales),
                               novel_views=base.novel_views if novel is None else novel,
                               view_bank=base.view_bank if bank is None else bank,
                               lpips_net=lpips_net, attacks=args.attacks,
                               model_attacks=args.model_attack_prob, psnr_target=args.psnr_target, seed=args.seed,
                               weights=weights,
                               background=background_of(args))


def _load_model(args: argparse.Namespace):
    """(gaussians, cameras, images or None) from an INRIA folder or PLY + cameras."""
    from gsw.camera import load_inria_cameras
    from gsw.cli.common import resized_notice
    from gsw.io import load_gaussians

    src = Path(args.input)
    if src.is_dir():
        from gsw.data import load_inria_model

        with reading(src):
            model = load_inria_model(src, images_dir=args.images, background=background_of(args),
                                     resize_images=args.resize_images)
        resized_notice("embed", model.resized)
        return model.gaussians, model.cameras, model.images
    if not args.cameras:  # a bare model: embed() samples views around its content
        return load_gaussians(src), None, None
    with reading(args.cameras):
        cameras = load_inria_cameras(args.cameras)
    return load_gaussians(src), cameras, None


def cmd_embed(args: argparse.Namespace) -> int:
    """Watermarks a model; writes a new INRIA model folder (with ``watermark.json``) atomically, then verifies it
    (:func:`~gsw.cli.common.verify_written_model`); exit status 1 if the mark is not detected at ``--fpr``."""
    from gsw.cli.common import split_views, verify_written_model
    from gsw.cli.metadata import watermark_record, write_watermark_json
    from gsw.data import save_inria_model
    from gsw.decoder.zoo import load_decoder
    from gsw.device import resolve_device
    from gsw.eval.grid import decoder_fingerprint
    from gsw.mark.embed import embed

    message, num_bits = message_from_args(args, required=False)
    check_readout_origin(args.readout, "random" if args.message is None else "chosen", num_bits)
    decoder = readout_decoder(args.readout, num_bits)
    check_record(args, message, num_bits, decoder)
    origin = chosen_message_note(args, "embed")
    config = embed_config(args)
    device = resolve_device(args.device)
    output, inputs = Path(args.output), input_paths(args, "input", "cameras", "images", "registry")
    check_output(output, inputs, args.force)  # before loading; output_folder checks again and commits exclusively
    g, cams, images = _load_model(args)
    bare = cams is None  # a bare model: embed() samples views around its content; the check uses those views
    used, checked, held_out = split_views(0 if bare else len(cams), args.holdout_every)
    with output_folder(output, inputs, args.force) as tmp:
        res = embed(g.to(device), None if bare else [cams[i] for i in used], message=message, num_bits=num_bits,
                    images=None if images is None else list(images[used].to(device)), config=config,
                    decoder=decoder, progress=not args.no_progress)
        if bare:
            cams, checked = res.cameras, list(range(len(res.cameras)))
        save_inria_model(tmp, res.gaussians, cams, iteration=0)
        stats = dict(gaussians_in=len(g), gaussians_out=len(res.gaussians),
                     pruned=res.prune.num_removed if res.prune else 0,
                     split=res.split.num_split if res.split else 0,
                     mean_bit_accuracy=sum(res.bit_accuracy) / len(res.bit_accuracy),
                     mean_psnr=sum(res.psnr) / len(res.psnr), timings=res.timings)
        record = watermark_record(num_bits=num_bits, background=config.background, cameras=cams,
                                  decoder=decoder_fingerprint(load_decoder(num_bits) if decoder is None else decoder),
                                  config=config, stats=stats, message_origin=origin)
        write_watermark_json(tmp, record)
        size = record["resolution"] and (record["resolution"]["width"], record["resolution"]["height"])
        recorded = record_issued(args, res.message, decoder, gaussians=res.gaussians, size=size,
                                 background=config.background, origin=origin)
    check = verify_written_model(output, cams, checked, held_out, res.message, num_bits=num_bits,
                                 background=config.background, fpr=args.fpr, device=device, origin=origin,
                                 decoder=decoder)
    issued, note = issued_summary(recorded, res.message_hex, res.message.int().tolist())
    if args.json:
        print_json(dict(**issued, output=str(output), verification=check, **record))
    else:
        print(f"embedded into {output}: {len(res.gaussians):,} Gaussians, mean bit accuracy "
              f"{100 * stats['mean_bit_accuracy']:.2f} %, mean PSNR {stats['mean_psnr']:.2f} dB; {note}")
        print(f"verified {output} on {check['where']}: bit accuracy {100 * check['bit_accuracy']:.2f} %, "
              f"p = {check['p_value']:.2e} ({'' if check['detected'] else 'NOT '}detected at p <= {args.fpr:g})")
    if not check["detected"]:
        not_detectable_warning("embed", args.fpr, [f"{output} (p = {check['p_value']:.2e} on {check['where']})"],
                               "raise --epochs or --message-weight")
        return 1
    return 0


# ------------------------------------------------------------------------------------------------ embed-image


def _image_targets(sources: list[Path], output: Path) -> list[Path]:
    """Output file per input: ``output`` itself (one input, a .png) or ``output/<stem>.png``."""
    if len(sources) == 1:
        if output.suffix.lower() != ".png":
            raise ValueError(f"output {output} must be a .png (a lossy format would weaken the watermark before "
                             "it ships)")
        return [output]
    stems = [s.stem for s in sources]
    if len(set(stems)) != len(stems):
        raise ValueError("several inputs share a file name; their outputs (<name>.png) would collide")
    return [output / f"{stem}.png" for stem in stems]


def cmd_embed_image(args: argparse.Namespace) -> int:
    """Watermarks 2-D images; writes new PNGs atomically; exit status 1 if one is not detectable.

    One input: ``--output`` is the new .png file. Several: ``--output`` is a new folder that receives
    ``<input stem>.png`` for each input (written into a temporary folder renamed into place).
    """
    import torch

    from gsw.data.images import read_image, read_rgb, write_image
    from gsw.mark.image import ImageEmbedConfig, embed_images

    sources, output = [Path(p) for p in args.images], Path(args.output)
    message, num_bits = message_from_args(args, required=False)
    targets = _image_targets(sources, output)
    check_readout_origin(args.readout, "random" if args.message is None else "chosen", num_bits)
    decoder = readout_decoder(args.readout, num_bits)
    check_record(args, message, num_bits, decoder)
    origin = chosen_message_note(args, "embed-image")
    images = [read_rgb(p) for p in sources]
    cfg = ImageEmbedConfig(psnr=args.psnr, steps=args.steps, seed=args.seed, device=args.device)

    def run():
        return embed_images(images, message, num_bits=num_bits, config=cfg, decoder=decoder, batch_size=args.batch,
                            progress=not args.no_progress)

    def record():  # before the outputs appear: a registry error leaves no unrecorded watermarked image
        sizes = {tuple(r.image.shape[:0:-1]) for r in results}
        return record_issued(args, results[0].message, decoder, size=sizes.pop() if len(sizes) == 1 else None,
                             origin=origin)

    inputs = [*sources, *input_paths(args, "registry")]
    with (output_file if len(sources) == 1 else output_folder)(output, inputs, args.force) as tmp:
        results = run()
        for target, res in zip(targets, results):
            write_image(tmp if len(sources) == 1 else tmp / target.name, res.image)
        recorded = record()
    for target, res in zip(targets, results):
        if not torch.equal(read_image(target), res.image.cpu()):
            raise RuntimeError(f"{target} does not hold the image that was verified")
    rows = [dict(image=str(t), source=str(s), psnr=r.psnr, bit_accuracy=r.bit_accuracy,
                 p_value=r.p_value, seconds=r.seconds) for t, s, r in zip(targets, sources, results)]
    issued, note = issued_summary(recorded, results[0].message_hex, results[0].message.int().tolist())
    if args.json:
        print_json(dict(**issued, images=rows))
    else:
        for r in rows:
            print(f"embedded into {r['image']}: PSNR {r['psnr']:.2f} dB, read back "
                  f"{100 * r['bit_accuracy']:.2f} % of the bits (p = {r['p_value']:.2e}) in {r['seconds']:.1f} s")
        print(note)
    weak = [r["image"] for r in rows if r["p_value"] > DETECTION_FPR]
    if weak:
        not_detectable_warning("embed-image", DETECTION_FPR, weak, "raise --steps or lower --psnr")
        return 1
    return 0


# ------------------------------------------------------------------------------------------------ extract, verify


def _size(text: str) -> tuple[int, int]:
    """argparse type: ``WIDTHxHEIGHT`` -> (width, height)."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 800x800, got {text!r}") from None
    if width <= 0 or height <= 0:
        raise argparse.ArgumentTypeError(f"sizes must be positive, got {text!r}")
    return width, height


def cmd_extract(args: argparse.Namespace) -> int:
    """Reads the message bits of images (through ``--readout``)."""
    from gsw.io.video import load_named_images_or_video
    from gsw.mark.detect import extract

    decoder, results = readout_decoder(args.readout, args.bits), []
    for path, img in load_named_images_or_video(args.images):
        ext = extract(img, num_bits=args.bits, decoder=decoder,
                      embed_size=args.embed_size and args.embed_size[::-1])
        results.append(dict(image=path, bits=ext.bits[0].int().tolist(),
                            hex=ext.hex[0] if args.bits % 4 == 0 else None))
    if args.json:
        print_json(results)
    else:
        for r in results:
            print(f"{r['hex'] or ''.join(map(str, r['bits']))}  {r['image']}")
    return 0


def _model_views(folder: str, info, device):
    """((gaussians, cameras), view names) of ``verify --model``: the cameras at the embedding resolution."""
    from gsw.cli.metadata import at_resolution
    from gsw.data import load_inria_model

    with reading(folder):
        model = load_inria_model(folder)
    cameras = model.cameras if info is None else at_resolution(model.cameras, info)
    return (model.gaussians.to(device), cameras), [c.name or f"view {i}" for i, c in enumerate(cameras)]


def _check_decoder(info, num_bits: int, readout: str) -> None:
    """A model embedded through the other ``--readout`` (its ``watermark.json`` fingerprint says which) is refused,
    naming the flag to use; one embedded with another decoder than the one this gsw ships does not read back: a
    warning says so.

    Raises:
        ValueError: ``watermark.json`` records the shipped decoder read through another readout than ``readout``.
    """
    from gsw.decoder.zoo import load_decoder
    from gsw.eval.grid import decoder_fingerprint
    from gsw.eval.grid.store import legacy_decoder_fingerprint

    if info is None or num_bits != info.num_bits:
        return
    shipped = load_decoder(num_bits)
    by_print = {}
    for r in READOUTS:
        d = readout_decoder(r, num_bits, shipped)
        by_print.update({decoder_fingerprint(d): r, legacy_decoder_fingerprint(d): r})  # and as written before 2026-11-28
    recorded = by_print.get(info.decoder)
    if recorded is None:
        print(f"gsw verify: warning: the model was watermarked with another {num_bits}-bit decoder "
              f"(gsw {info.gsw_version}, {info.path}); detection may fail", file=sys.stderr)
    elif recorded != readout:
        raise ValueError(f"the model was watermarked through the {recorded} readout ({info.path}) but this run reads "
                         f"it through --readout {readout}, which cannot detect it; pass --readout {recorded}")


def cmd_verify(args: argparse.Namespace) -> int:
    """Tests images or a model for a message (through ``--readout``; a model's ``watermark.json`` that records the
    other readout is refused); exit status 0 if detected at the FPR, else 1."""
    from gsw.cli.metadata import read_watermark_json
    from gsw.device import resolve_device
    from gsw.mark.detect import verify

    if args.model and args.images:
        raise ValueError("pass images or --model, not both")
    if not args.model and not args.images:
        raise ValueError("pass images or --model")
    info = read_watermark_json(args.model) if args.model else None
    message, num_bits = message_from_args(args, required=True, stored_bits=None if info is None else info.num_bits)
    _check_decoder(info, num_bits, args.readout)
    background = background_of(args, None if info is None else info.background)
    device = resolve_device(args.device)
    if args.model:
        source, names = _model_views(args.model, info, device)
    else:
        from gsw.io.video import load_named_images_or_video

        named = load_named_images_or_video(args.images)
        source, names = [img.to(device) for _, img in named], [n for n, _ in named]
    embed_size = None if info is None or info.resolution is None else (info.resolution[1], info.resolution[0])
    stored_chosen = info is not None and info.message_origin == "chosen"
    origin = "chosen" if args.chosen_message or stored_chosen else "random"
    check_readout_origin(args.readout, origin, num_bits)
    v = verify(source, message, num_bits=num_bits, decoder=readout_decoder(args.readout, num_bits),
               background=background, embed_size=embed_size, origin=origin)
    detected = v.detected(args.fpr)
    if args.json:
        print_json(dict(detected=detected, p_value=v.p_value, fpr=args.fpr, num_bits=num_bits, origin=origin,
                        test=v.test, background=list(background) if args.model else None,
                        views=[dict(name=n, bit_accuracy=a, p_value=p)
                               for n, a, p in zip(names, v.bit_accuracy, v.p_values)]))
    else:
        for n, a, p in zip(names, v.bit_accuracy, v.p_values):
            print(f"{100 * a:6.2f} %  p={p:.2e}  {n}")
        test = {"exact": "random message: exact test", "calibrated": "chosen message: calibrated null model",
                "fair": "chosen message: fair coin (this decoder has no null model; bit correlations not counted)"
                }[v.test]
        print(f"{'DETECTED' if detected else 'not detected'}: combined p-value {v.p_value:.2e} "
              f"(threshold {args.fpr:g}; {test})")
    return 0 if detected else 1
