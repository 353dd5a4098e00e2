"""The `gsw` command line: demo, embed, embed-image, extract, verify, eval, eval-grid, train, export, render, info.

Run `gsw <command> --help` for the options of each command.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Sequence

import torch

from gsw.stats import DETECTION_FPR


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _check_output(output: Path, inputs: Sequence[Path], force: bool) -> None:
    """Refuses an output (file or folder) that is, holds or lies inside an input, or exists without ``force``."""
    out = output.resolve()
    for src in inputs:
        src = src.resolve()
        if out == src or out in src.parents or src in out.parents:
            raise ValueError(f"output {output} overlaps the input {src}; inputs are never overwritten")
    if out.exists() and not force:
        raise ValueError(f"output {output} exists; pass --force to replace it")


def _atomic_output_dir(output: Path, inputs: Sequence[Path], force: bool) -> Path:
    """Checks an output folder and returns a fresh temporary sibling to write into."""
    import tempfile

    _check_output(output, inputs, force)
    out = output.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))


def _publish(tmp: Path, output: Path) -> None:
    """Moves a finished temporary folder into place (replacing an old output only at the end)."""
    import shutil

    if output.exists():
        old = output.with_name(f".{output.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        output.rename(old)
        tmp.rename(output)
        shutil.rmtree(old, ignore_errors=True)
    else:
        tmp.rename(output)


def _embed_config(args: argparse.Namespace):
    from gsw.mark.embed import EmbedConfig
    from gsw.mark.loss import LossWeights

    lpips_net = None if args.lpips == "none" else args.lpips
    weights = LossWeights(lpips=0.0) if lpips_net is None else LossWeights()
    if args.message_weight is not None:
        weights = dataclasses.replace(weights, message=args.message_weight)
    return EmbedConfig(epochs=args.epochs, fgd=not args.no_fgd, mask=args.mask,
                       lpips_net=lpips_net, attacks=args.attacks, model_attacks=args.model_attack_prob,
                       seed=args.seed, weights=weights,
                       background=(1.0, 1.0, 1.0) if args.white else (0.0, 0.0, 0.0))


def _message_arg(args: argparse.Namespace):
    if getattr(args, "key", None):
        return f"key:{args.key}"
    return args.message


def cmd_demo(args: argparse.Namespace) -> int:
    """Built-in scene -> 32-bit watermark -> extraction; prints a table, writes PNGs."""
    import gsw
    from gsw.mark.embed import EmbedConfig, embed, verify
    from gsw.data.images import write_image
    from gsw.mark.loss import LossWeights
    from gsw.metrics.image import psnr, ssim
    from gsw.scenes import default_scene

    start = time.perf_counter()
    out_dir = Path(args.output)
    out_dir.mkdir(parents=True, exist_ok=True)
    scene = default_scene(width=args.size, height=args.size, n_cameras=args.views)
    bg = tuple(float(v) for v in torch.as_tensor(scene.background).flatten())
    g, cams = scene.gaussians, scene.cameras
    print(f"gsw {gsw.__version__} demo: built-in scene, {len(g):,} Gaussians (SH {g.sh_degree}), "
          f"{len(cams)} views at {args.size}x{args.size}, {args.bits}-bit message, "
          f"{torch.get_num_threads()} threads", flush=True)
    lpips_net = None if args.lpips == "none" else args.lpips
    cfg = EmbedConfig(epochs=args.epochs, background=bg, seed=args.seed, lpips_net=lpips_net,
                      weights=LossWeights() if lpips_net else LossWeights(lpips=0.0))
    res = embed(g, cams, message=_message_arg(args), num_bits=args.bits, config=cfg,
                progress=not args.no_progress)
    held_out = default_cameras_between(cams, args.size)
    verdict = verify((res.gaussians, held_out), res.message, background=bg)
    before = verify((g, held_out), res.message, background=bg)
    quality = []
    lp = None
    if lpips_net:
        from gsw.metrics.lpips import lpips as lpips_fn
        lp = lpips_fn
    with torch.no_grad():
        for i, cam in enumerate(held_out):
            a = gsw.rasterize(g, cam, background=bg).image.clamp(0, 1)
            b = gsw.rasterize(res.gaussians, cam, background=bg).image.clamp(0, 1)
            quality.append((float(psnr(b, a)), float(ssim(b, a)),
                            float(lp(b[None], a[None], net=lpips_net)) if lp else float("nan")))
            if i == 0:
                write_image(out_dir / "original.png", a)
                write_image(out_dir / "watermarked.png", b)
                write_image(out_dir / "difference_x2.png", ((b - a).abs() * 2).clamp(0, 1))
    mean = lambda xs: sum(xs) / len(xs)  # noqa: E731
    rows = [
        ("message", res.message_hex),
        ("bit accuracy, held-out views", f"{100 * mean(verdict.bit_accuracy):.2f} %"),
        ("bit accuracy, same views before embedding", f"{100 * mean(before.bit_accuracy):.2f} %"),
        (f"views with p <= {DETECTION_FPR:g}", f"{sum(p <= DETECTION_FPR for p in verdict.p_values)} / {len(held_out)}"),
        ("combined p-value", f"{verdict.p_value:.2e}"),
        ("PSNR vs original render", f"{mean([q[0] for q in quality]):.2f} dB"),
        ("SSIM vs original render", f"{mean([q[1] for q in quality]):.4f}"),
        ("LPIPS vs original render", f"{mean([q[2] for q in quality]):.4f}" if lp else "off"),
        ("Gaussians: input / after FGD",
         f"{len(g):,} / {len(res.gaussians):,} (pruned {res.prune.num_removed:,}, split "
         f"{res.split.num_split:,})" if res.prune else f"{len(g):,} (FGD off)"),
        ("time: FGD / fine-tune / total", f"{res.timings['fgd']:.1f} s / {res.timings['finetune']:.1f} s / "
         f"{time.perf_counter() - start:.1f} s"),
        ("images", f"{out_dir}/original.png, watermarked.png, difference_x2.png"),
    ]
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k:<{width}}  {v}")
    if args.json:
        json.dump(dict(rows), sys.stdout, indent=2)
        print()
    return 0


def default_cameras_between(cams: Sequence, size: int) -> list:
    """Held-out views of the built-in scene: the orbit shifted by half a step."""
    from gsw.scenes import default_cameras

    n = len(cams)
    return default_cameras(n, size, size, azimuth_offset_deg=180.0 / n)


def _load_model(args: argparse.Namespace):
    """(gaussians, cameras, images or None, input paths) from an INRIA folder or PLY + cameras."""
    import gsw
    from gsw.camera import load_inria_cameras

    src = Path(args.input)
    if src.is_dir():
        from gsw.data import load_inria_model

        model = load_inria_model(src, images_dir=args.images, background=(1.0, 1.0, 1.0) if args.white else (0.0, 0.0, 0.0))
        return model.gaussians, model.cameras, model.images, [src]
    if not args.cameras:
        raise ValueError(f"{src} is a file: pass --cameras cameras.json (or give an INRIA model folder)")
    return gsw.load_gaussians(src), load_inria_cameras(args.cameras), None, [src, Path(args.cameras)]


def cmd_embed(args: argparse.Namespace) -> int:
    """Watermarks a model; writes a new INRIA model folder atomically."""
    from gsw.data import save_inria_model
    from gsw.mark.embed import embed

    g, cams, images, inputs = _load_model(args)
    output = Path(args.output)
    tmp = _atomic_output_dir(output, inputs, args.force)
    try:
        res = embed(g, cams, message=_message_arg(args), num_bits=args.bits,
                    images=None if images is None else list(images), config=_embed_config(args),
                    progress=not args.no_progress)
        save_inria_model(tmp, res.gaussians, cams, iteration=0)
        summary = dict(message=res.message_hex, bits=res.message.int().tolist(),
                       gaussians_in=len(g), gaussians_out=len(res.gaussians),
                       pruned=res.prune.num_removed if res.prune else 0,
                       split=res.split.num_split if res.split else 0,
                       mean_bit_accuracy=sum(res.bit_accuracy) / len(res.bit_accuracy),
                       mean_psnr=sum(res.psnr) / len(res.psnr), timings=res.timings)
        (tmp / "watermark.json").write_text(json.dumps(summary, indent=2) + "\n")
        _publish(tmp, output)
    except BaseException:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if args.json:
        json.dump(summary, sys.stdout, indent=2)
        print()
    else:
        print(f"embedded {res.message_hex} into {output}: {len(res.gaussians):,} Gaussians, "
              f"mean bit accuracy {100 * summary['mean_bit_accuracy']:.2f} %, mean PSNR "
              f"{summary['mean_psnr']:.2f} dB (keep the message: watermark.json)")
    return 0


def cmd_embed_image(args: argparse.Namespace) -> int:
    """Watermarks 2-D images; writes new PNGs atomically; exit status 1 if one is not detectable.

    One input: ``--output`` is the new .png file. Several: ``--output`` is a new folder that receives
    ``<input stem>.png`` for each input (written into a temporary folder renamed into place).
    """
    from gsw.data.images import read_image, write_image
    from gsw.mark.image import ImageEmbedConfig, embed_images

    sources, output = [Path(p) for p in args.images], Path(args.output)
    single = len(sources) == 1
    if single:
        if output.suffix.lower() != ".png":
            raise ValueError(f"output {output} must be a .png (a lossy format would weaken the watermark before "
                             "it ships)")
        _check_output(output, sources, args.force)
        targets = [output]
    else:
        stems = [s.stem for s in sources]
        if len(set(stems)) != len(stems):
            raise ValueError("several inputs share a file name; their outputs (<name>.png) would collide")
        targets = [output / f"{stem}.png" for stem in stems]
    images = _read_images(sources)
    cfg = ImageEmbedConfig(psnr=args.psnr, steps=args.steps, seed=args.seed, device=args.device)
    tmp = None if single else _atomic_output_dir(output, sources, args.force)
    try:
        results = embed_images(images, _message_arg(args), num_bits=args.bits, config=cfg, batch_size=args.batch,
                               progress=not args.no_progress)
        if tmp is None:
            output.parent.mkdir(parents=True, exist_ok=True)
            write_image(output, results[0].image)
        else:
            for target, res in zip(targets, results):
                write_image(tmp / target.name, res.image)
            _publish(tmp, output)
    except BaseException:
        if tmp is not None:
            import shutil

            shutil.rmtree(tmp, ignore_errors=True)
        raise
    for target, res in zip(targets, results):
        if not torch.equal(read_image(target), res.image.cpu()):
            raise RuntimeError(f"{target} does not hold the image that was verified")
    rows = [dict(image=str(t), source=str(s), message=r.message_hex, psnr=r.psnr, bit_accuracy=r.bit_accuracy,
                 p_value=r.p_value, seconds=r.seconds) for t, s, r in zip(targets, sources, results)]
    if args.json:
        json.dump(dict(message=results[0].message_hex, bits=results[0].message.int().tolist(),
                       images=rows), sys.stdout, indent=2)
        print()
    else:
        for r in rows:
            print(f"embedded {r['message']} into {r['image']}: PSNR {r['psnr']:.2f} dB, read back "
                  f"{100 * r['bit_accuracy']:.2f} % of the bits (p = {r['p_value']:.2e}) in {r['seconds']:.1f} s")
    weak = [r["image"] for r in rows if r["p_value"] > DETECTION_FPR]
    if weak:
        print(f"gsw embed-image: warning: not detectable at p <= {DETECTION_FPR:g}: {', '.join(weak)} "
              "(raise --steps or lower --psnr)", file=sys.stderr)
        return 1
    return 0


def _read_images(paths: Sequence[str]) -> list:
    from gsw.data.images import read_image

    images = []
    for p in paths:
        img = read_image(p)
        if img.shape[0] == 4:  # composite RGBA on black, as renders are
            img = img[:3] * img[3:]
        images.append(img)
    return images


def cmd_extract(args: argparse.Namespace) -> int:
    """Reads the message bits of images."""
    from gsw.mark.embed import extract

    images = _read_images(args.images)
    results = []
    for path, img in zip(args.images, images):
        ext = extract(img, num_bits=args.bits)
        results.append(dict(image=path, bits=ext.bits[0].int().tolist(),
                            hex=ext.hex[0] if args.bits % 4 == 0 else None))
    if args.json:
        json.dump(results, sys.stdout, indent=2)
        print()
    else:
        for r in results:
            print(f"{r['hex'] or ''.join(map(str, r['bits']))}  {r['image']}")
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    """Tests images or a model for a message; exit status 0 if detected at the FPR, else 1."""
    from gsw.mark.embed import verify

    message = _message_arg(args)
    if message is None:
        raise ValueError("pass --message HEX or --key SECRET")
    if args.model:
        from gsw.data import load_inria_model

        model = load_inria_model(args.model)
        source = (model.gaussians, model.cameras)
        names = [c.name or f"view {i}" for i, c in enumerate(model.cameras)]
    else:
        if not args.images:
            raise ValueError("pass images or --model")
        source = _read_images(args.images)
        names = list(args.images)
    v = verify(source, message, num_bits=args.bits)
    detected = v.detected(args.fpr)
    if args.json:
        json.dump(dict(detected=detected, p_value=v.p_value, fpr=args.fpr,
                       views=[dict(name=n, bit_accuracy=a, p_value=p)
                              for n, a, p in zip(names, v.bit_accuracy, v.p_values)]), sys.stdout, indent=2)
        print()
    else:
        for n, a, p in zip(names, v.bit_accuracy, v.p_values):
            print(f"{100 * a:6.2f} %  p={p:.2e}  {n}")
        print(f"{'DETECTED' if detected else 'not detected'}: combined p-value {v.p_value:.2e} "
              f"(threshold {args.fpr:g})")
    return 0 if detected else 1


def cmd_eval(args: argparse.Namespace) -> int:
    """Invisibility + robustness report of a watermarked INRIA folder against its original."""
    from gsw.data import load_inria_model
    from gsw.eval.report import evaluate_watermark

    message = _message_arg(args)
    if message is None:
        raise ValueError("pass --message HEX or --key SECRET")
    marked = load_inria_model(args.watermarked)
    original = load_inria_model(args.original)
    cams = marked.cameras if args.views is None else marked.cameras[: args.views]
    report = evaluate_watermark(marked.gaussians, original.gaussians, cams, message,
                                num_bits=args.bits, official=args.official,
                                background=(1.0, 1.0, 1.0) if args.white else (0.0, 0.0, 0.0),
                                lpips_net=None if args.lpips == "none" else args.lpips)
    text = report.to_markdown()
    if args.output:
        from gsw._atomic import atomic_write

        with atomic_write(args.output, "w") as f:
            f.write(text)
    if args.json:
        json.dump(report.to_dict(), sys.stdout, indent=2)
        print()
    else:
        print(text, end="")
    return 0


def _grid_scene(args: argparse.Namespace):
    """The scene of `gsw eval-grid`: the built-in one or an INRIA model folder (+ its dataset)."""
    from gsw.eval.grid import default_grid_scene, load_grid_scene

    if args.scene == "default":
        misplaced = [flag for flag, value in (("--data", args.data), ("--downscale", args.downscale),
                                              ("--white", args.white)) if value]
        if misplaced:
            raise ValueError(f"{', '.join(misplaced)} apply to an INRIA model folder, not the built-in scene")
        return default_grid_scene(size=args.size or 64, views=args.train_views or 24, eval_views=args.eval_views)
    if args.size:
        raise ValueError("--size applies to the built-in scene; an INRIA model's views come from its cameras/data")
    return load_grid_scene(args.scene, args.data, downscale=args.downscale or 1.0, white=args.white,
                           train_views=args.train_views, eval_views=args.eval_views)


def cmd_eval_grid(args: argparse.Namespace) -> int:
    """Runs (or resumes) an evaluation grid: methods x bit lengths x seeds on one scene."""
    from gsw.eval.grid import GridSpec, lpips_loss_overrides, run_grid

    if args.plots:
        from gsw.eval.plots import require_matplotlib

        require_matplotlib()  # fail before hours of computing, not after
    spec = GridSpec(methods=tuple(args.methods), bits=tuple(args.bits), seeds=tuple(args.seeds),
                    epochs=args.epochs, image_attacks=tuple(args.image_attacks),
                    model_attacks=tuple(args.model_attacks), sweeps=tuple(args.sweeps),
                    embed=lpips_loss_overrides(None if args.lpips == "none" else args.lpips), fpr=args.fpr,
                    lpips_net=None if args.metric_lpips == "none" else args.metric_lpips)
    from gsw.train import resolve_device

    scene = _grid_scene(args).to(resolve_device(args.device))
    summary = run_grid(spec, scene, args.output, resume=args.resume, force=args.force,
                       progress=not args.no_progress)
    plots = []
    if args.plots:
        from gsw.eval.plots import plot_grid

        plots = plot_grid(args.output)
    if args.json:
        json.dump(summary.to_dict(), sys.stdout, indent=2)
        print()
    else:
        print(summary.to_markdown())
        print(f"{summary.computed} cells computed, {summary.reused} reused; results in {args.output}/ "
              f"(summary.md, summary.json, cells/){''.join(f', {p}' for p in plots)}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    """Renders a PLY/.splat model from cameras.json or an orbit."""
    import gsw
    from gsw.camera import load_inria_cameras
    from gsw.data.images import write_image

    model = Path(args.model)
    g = gsw.load_gaussians(model)
    if args.cameras:
        cams = load_inria_cameras(args.cameras)
    else:
        center = g.means.median(dim=0).values
        radius = args.radius or float(3.0 * (g.means - center).norm(dim=1).median())
        cams = gsw.orbit_cameras(center.tolist(), radius, args.orbit, width=args.width,
                                 height=args.height)
    out_dir = Path(args.output)
    if out_dir.resolve() == model.resolve().parent and not args.force:
        raise SystemExit("refusing to write renders into the model's own folder; pass --force")
    out_dir.mkdir(parents=True, exist_ok=True)
    bg = (1.0, 1.0, 1.0) if args.white else (0.0, 0.0, 0.0)
    with torch.no_grad():
        for i, cam in enumerate(cams):
            out = gsw.rasterize(g, cam, background=bg)
            name = cam.name or f"view_{i:03d}"
            write_image(out_dir / f"{Path(name).stem}.png", out.image)
    print(f"rendered {len(cams)} views of {len(g):,} Gaussians to {out_dir}/")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    """Prints the build information as JSON."""
    import gsw

    json.dump(gsw.build_info(), sys.stdout, indent=2)
    print()
    return 0


def _add_eval_grid_parser(sub) -> None:
    from gsw.attacks.ops import IMAGE_ATTACKS, MODEL_ATTACK_NAMES, SWEEPS
    from gsw.eval.grid import METHODS, PAPER_MODEL_ATTACKS, GridSpec

    default = GridSpec()
    grid = sub.add_parser("eval-grid", help="methods x bit lengths x seeds: resumable results and paper tables",
                          description="Embeds every (method, bits, seed) cell, evaluates it on held-out views and "
                          "writes one JSON per cell, summary.json and summary.md (the paper's tables) into "
                          "--output; a rerun skips finished cells.")
    grid.add_argument("scene", help='INRIA model folder, or "default" for the built-in scene')
    grid.add_argument("--output", required=True, help="grid folder (created; reused to resume)")
    grid.add_argument("--data", help="the model's dataset (NeRF-synthetic / instant-ngp): train split to embed, "
                      "test split to evaluate (default: hold out every 8th of the model's cameras)")
    grid.add_argument("--downscale", type=float, help="image/camera size divisor of an INRIA model (default 1)")
    grid.add_argument("--white", action="store_true", help="white background (INRIA model; the built-in is white)")
    grid.add_argument("--size", type=_positive_int, help="render size of the built-in scene (default 64)")
    grid.add_argument("--train-views", type=_positive_int,
                      help="embedding views (built-in scene: orbit size, default 24; INRIA: evenly spaced subset)")
    grid.add_argument("--eval-views", type=_positive_int, help="use the first N evaluation views")
    grid.add_argument("--methods", nargs="*", default=list(default.methods), metavar="METHOD",
                      help=f"of {', '.join(METHODS)} (default: all)")
    grid.add_argument("--bits", nargs="*", type=_positive_int, choices=[32, 48, 64], default=list(default.bits))
    grid.add_argument("--seeds", nargs="*", type=int, default=list(default.seeds))
    grid.add_argument("--epochs", type=_positive_int, default=default.epochs)
    grid.add_argument("--image-attacks", nargs="*", default=list(default.image_attacks), metavar="ATTACK",
                      help=f"of {', '.join(IMAGE_ATTACKS)} (default: all)")
    grid.add_argument("--model-attacks", nargs="*", default=list(default.model_attacks), metavar="ATTACK",
                      help=f"of {', '.join(MODEL_ATTACK_NAMES)} "
                      f"(default: the paper's {', '.join(PAPER_MODEL_ATTACKS)})")
    grid.add_argument("--sweeps", nargs="*", default=list(default.sweeps), metavar="ATTACK",
                      help=f"robustness curves, of {', '.join(SWEEPS)} (default: all)")
    grid.add_argument("--lpips", choices=["vgg", "alex", "none"], default="vgg",
                      help="LPIPS term of the embedding loss")
    grid.add_argument("--metric-lpips", choices=["vgg", "alex", "none"], default="vgg",
                      help="LPIPS network of the invisibility metric")
    grid.add_argument("--fpr", type=float, default=default.fpr, help="false-positive rate of a detection")
    grid.add_argument("--device", default="cpu", help="cpu, cuda[:N] or auto (default: cpu)")
    grid.add_argument("--resume", action=argparse.BooleanOptionalAction, default=True,
                      help="keep finished cells of an earlier run (default); --no-resume recomputes them")
    grid.add_argument("--force", action="store_true", help="replace the settings of a folder holding another grid")
    grid.add_argument("--plots", action="store_true", help="also draw plots/*.png (needs matplotlib)")
    grid.add_argument("--no-progress", action="store_true")
    grid.add_argument("--json", action="store_true", help="print the summary as JSON instead of tables")
    grid.set_defaults(func=cmd_eval_grid)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the `gsw` command."""
    from gsw.mark.image import ImageEmbedConfig

    parser = argparse.ArgumentParser(prog="gsw", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="watermark the built-in scene and read it back (no downloads)")
    demo.add_argument("--output", default="gsw-demo", help="output folder (default: gsw-demo)")
    demo.add_argument("--size", type=_positive_int, default=256,
                      help="render size (pixels; the decoder reads the 4x smaller LL2 subband)")
    demo.add_argument("--views", type=_positive_int, default=24, help="training views")
    demo.add_argument("--epochs", type=_positive_int, default=8)
    demo.add_argument("--bits", type=_positive_int, default=32)
    demo.add_argument("--message", help="hex message (default: random)")
    demo.add_argument("--key", help="derive the message from a secret key")
    demo.add_argument("--lpips", choices=["vgg", "alex", "none"], default="alex")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--no-progress", action="store_true")
    demo.add_argument("--json", action="store_true", help="also print the table as JSON")
    demo.set_defaults(func=cmd_demo)

    emb = sub.add_parser("embed", help="watermark a model, writing a new INRIA model folder")
    emb.add_argument("input", help="INRIA model folder, or a .ply/.splat with --cameras")
    emb.add_argument("--cameras", help="INRIA cameras.json (with a .ply/.splat input)")
    emb.add_argument("--images", help="folder of the training images (optional, for FGD)")
    emb.add_argument("--output", required=True, help="new model folder (never the input)")
    emb.add_argument("--force", action="store_true", help="replace an existing output folder")
    emb.add_argument("--bits", type=_positive_int, default=32, choices=[32, 48, 64])
    emb.add_argument("--message", help="hex message (default: random)")
    emb.add_argument("--key", help="derive the message from a secret key")
    emb.add_argument("--epochs", type=_positive_int, default=8)
    emb.add_argument("--mask", choices=["exp", "stega", "none"], default="exp")
    emb.add_argument("--lpips", choices=["vgg", "alex", "none"], default="vgg")
    emb.add_argument("--no-fgd", action="store_true", help="skip frequency-guided densification")
    emb.add_argument("--attacks", type=float, default=0.0, help="train-time image-attack probability")
    emb.add_argument("--model-attack-prob", type=float, default=0.0,
                     help="train-time model-attack probability (parameter noise / SH degree 0)")
    emb.add_argument("--message-weight", type=float, default=None,
                     help="weight of the message loss (default: LossWeights.message)")
    emb.add_argument("--white", action="store_true", help="white background")
    emb.add_argument("--seed", type=int, default=0)
    emb.add_argument("--no-progress", action="store_true")
    emb.add_argument("--json", action="store_true")
    emb.set_defaults(func=cmd_embed)

    emi = sub.add_parser("embed-image", help="watermark 2-D images (PNG out), readable by extract/verify")
    emi.add_argument("images", nargs="+", help="input images (PNG, JPEG, ...; alpha is composited on black)")
    emi.add_argument("--output", required=True,
                     help="new .png file (one input) or new folder of <name>.png files (several); never an input")
    emi.add_argument("--force", action="store_true", help="replace an existing output")
    emi.add_argument("--batch", type=_positive_int, default=8, help="same-size images optimised together (default %(default)s)")
    emi.add_argument("--bits", type=_positive_int, default=32, choices=[32, 48, 64])
    emi.add_argument("--message", help="hex message (default: random)")
    emi.add_argument("--key", help="derive the message from a secret key")
    emi.add_argument("--psnr", type=float, default=ImageEmbedConfig.psnr, help="PSNR of the watermark in dB (higher = fainter and less robust; default %(default)s)")
    emi.add_argument("--steps", type=int, default=ImageEmbedConfig.steps, help="optimisation steps (more = more robust, linear time; default %(default)s)")
    emi.add_argument("--seed", type=int, default=0)
    emi.add_argument("--device", default="auto", help="auto, cpu or cuda")
    emi.add_argument("--no-progress", action="store_true")
    emi.add_argument("--json", action="store_true")
    emi.set_defaults(func=cmd_embed_image)

    ext = sub.add_parser("extract", help="read the message bits of images")
    ext.add_argument("images", nargs="+")
    ext.add_argument("--bits", type=_positive_int, default=32, choices=[32, 48, 64])
    ext.add_argument("--json", action="store_true")
    ext.set_defaults(func=cmd_extract)

    ver = sub.add_parser("verify", help="test images or a model for a message (exit 0 = detected)")
    ver.add_argument("images", nargs="*")
    ver.add_argument("--model", help="INRIA model folder to render instead of images")
    ver.add_argument("--message", help="hex message")
    ver.add_argument("--key", help="secret key the message was derived from")
    ver.add_argument("--bits", type=_positive_int, default=32, choices=[32, 48, 64])
    ver.add_argument("--fpr", type=float, default=DETECTION_FPR, help="false-positive rate of the decision")
    ver.add_argument("--json", action="store_true")
    ver.set_defaults(func=cmd_verify)

    ev = sub.add_parser("eval", help="invisibility and robustness report of a watermarked model")
    ev.add_argument("watermarked", help="watermarked INRIA model folder (its cameras are the views)")
    ev.add_argument("--original", required=True, help="the INRIA model folder before embedding")
    ev.add_argument("--message", help="hex message")
    ev.add_argument("--key", help="secret key the message was derived from")
    ev.add_argument("--bits", type=_positive_int, default=32, choices=[32, 48, 64])
    ev.add_argument("--views", type=_positive_int, default=None, help="use the first N cameras")
    ev.add_argument("--official", action="store_true", help="also the official code's attack variants")
    ev.add_argument("--lpips", choices=["vgg", "alex", "none"], default="vgg")
    ev.add_argument("--white", action="store_true", help="white background")
    ev.add_argument("--output", help="also write the markdown report to this file")
    ev.add_argument("--json", action="store_true")
    ev.set_defaults(func=cmd_eval)

    _add_eval_grid_parser(sub)

    from gsw.cli.train import add_train_parser, run_train

    add_train_parser(sub).set_defaults(func=run_train)

    from gsw.cli.export import register as register_export

    register_export(sub)

    render = sub.add_parser("render", help="render a .ply/.splat model to PNGs")
    render.add_argument("model", help="INRIA point_cloud.ply or .splat file")
    render.add_argument("--cameras", help="INRIA cameras.json (default: an orbit)")
    render.add_argument("--orbit", type=_positive_int, default=8, help="orbit views")
    render.add_argument("--radius", type=float, default=None, help="orbit radius")
    render.add_argument("--width", type=_positive_int, default=512)
    render.add_argument("--height", type=_positive_int, default=512)
    render.add_argument("--white", action="store_true", help="white background")
    render.add_argument("--output", required=True, help="output folder")
    render.add_argument("--force", action="store_true", help="allow writing next to the model")
    render.set_defaults(func=cmd_render)

    info = sub.add_parser("info", help="print build information")
    info.set_defaults(func=cmd_info)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `gsw` command."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, RuntimeError, ImportError) as err:
        print(f"gsw {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
