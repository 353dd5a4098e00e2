"""``gsw export``: convert a model to PLY, compressed PLY, ``.splat`` or ``.spz``, checking its watermark.

The input is a model file (any format :func:`gsw.io.load_gaussians` reads) or an INRIA model folder (its latest
``point_cloud/iteration_*``). The output is written atomically and never over an input. When a message is
known (``--message`` / ``--key``, the folder's ``watermark.json`` when it holds one, or the registry's mark of this
very model, found by its hash), the bit accuracy is measured on a few views before and after the conversion
(:func:`gsw.io.convert.check_conversion`) and a warning is printed when it drops by more than one percentage point.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from gsw.camera import Camera
from gsw.gaussians import Gaussians
from gsw.io.formats import WRITABLE_FORMATS

__all__ = ["register", "run_export"]


def register(subparsers: Any) -> argparse.ArgumentParser:
    """Adds the ``export`` command to the ``gsw`` sub-parsers; returns its parser."""
    p = subparsers.add_parser("export", help="convert a model to ply / compressed-ply / splat / spz",
                              description="Converts a model file or INRIA folder to another format, atomically and "
                              "never over the input; with a known message (--message/--key, watermark.json, or "
                              "the registry's mark of this model) it reports the watermark's bit accuracy before "
                              "and after the conversion.")
    p.add_argument("model", help="model file (.ply, .compressed.ply, .splat, .spz, .pt, .ckpt) or INRIA folder")
    p.add_argument("--output", required=True, help="new model file (never an input)")
    p.add_argument("--format", choices=WRITABLE_FORMATS,
                   help="output format (default: from the output name; .compressed.ply is compressed-ply)")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.add_argument("--message", help="hex message to check (default: the folder's watermark.json)")
    p.add_argument("--key", help="secret key the message was derived from")
    p.add_argument("--bits", type=int, choices=[32, 48, 64], help="message length (default: watermark.json, or 32)")
    p.add_argument("--registry", metavar="FILE",
                   help="registry of issued marks: without --message/--key, the check reads the mark registered "
                        "for this very model (matched by its hash; the message is never printed)")
    p.add_argument("--views", type=int, default=4, help="views of the check (default %(default)s)")
    p.add_argument("--size", type=int, default=256, help="orbit view size when the model has no cameras")
    p.add_argument("--white", action="store_true", help="white render background for the check")
    p.add_argument("--no-check", action="store_true", help="skip the watermark check")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=run_export)
    return p


def _output_format(output: Path, requested: str | None) -> str:
    from gsw.io.formats import model_format  # noqa: PLC0415

    implied = model_format(output, for_writing=True)
    if requested is None:
        return implied
    if requested != implied and not (requested == "compressed-ply" and implied == "ply"):
        raise ValueError(f"--format {requested} does not match the output name {output.name} "
                         f"(which means {implied})")
    return requested


def _load(model: Path) -> tuple[Gaussians, list[Camera] | None, dict | None, Path]:
    """(gaussians, cameras or None, watermark.json content or None, the model file)."""
    from gsw.io import load_gaussians  # noqa: PLC0415

    if model.is_dir():
        from gsw.data import load_inria_model  # noqa: PLC0415

        loaded = load_inria_model(model)
        gaussians, cameras, folder = loaded.gaussians, loaded.cameras, model
        file = model / "point_cloud" / f"iteration_{loaded.iteration}" / "point_cloud.ply"
    else:
        gaussians, cameras, folder, file = load_gaussians(model), None, model.parent, model
    mark = folder / "watermark.json"
    info = json.loads(mark.read_text(encoding="utf-8")) if mark.is_file() else None
    return gaussians, cameras, info if isinstance(info, dict) else None, file


def _registered(registry: str, gaussians: Gaussians, file: Path) -> Any:
    """The :class:`~gsw.registry.Mark` that ``registry`` holds for this model (its ``model_hash`` is the file's or
    the Gaussians' hash), or None."""
    from gsw.registry import hash_gaussians, hash_model_file, open_registry  # noqa: PLC0415

    with open_registry(registry, create=False) as reg:
        found = reg.of_model(hash_gaussians(gaussians), hash_model_file(file))
    return found[-1] if found else None


def _message(args: argparse.Namespace, info: dict | None) -> tuple[Any, int | None, str]:
    """(message or None, number of bits, where it came from)."""
    if args.key:
        return f"key:{args.key}", args.bits or 32, "--key"
    if args.message:
        return args.message, args.bits, "--message"
    if info and isinstance(info.get("message"), str):
        bits = info.get("bits")
        return info["message"], args.bits or (len(bits) if isinstance(bits, list) else None), "watermark.json"
    return None, None, ""


def _check_views(gaussians: Gaussians, cameras: list[Camera] | None, n: int, size: int) -> tuple[list[Camera], str]:
    from gsw.io.convert import orbit_views  # noqa: PLC0415

    if n < 1:
        raise ValueError(f"--views must be >= 1, got {n}")
    if cameras:
        step = max(1, len(cameras) // n)
        return list(cameras[::step][:n]), "model cameras"
    return orbit_views(gaussians, n, size), f"orbit {size}x{size}"


def run_export(args: argparse.Namespace) -> int:
    """Converts ``args.model`` into ``args.output``; returns the exit status."""
    from gsw.cli.common import check_output, output_file  # noqa: PLC0415
    from gsw.io.convert import check_conversion  # noqa: PLC0415
    from gsw.io.formats import load_model, save_model  # noqa: PLC0415

    model, output = Path(args.model), Path(args.output)
    fmt = _output_format(output, args.format)
    check_output(output, [model], args.force)
    gaussians, cameras, info, file = _load(model)
    message, bits, source = (None, None, "") if args.no_check else _message(args, info)
    mark = None
    if message is None and args.registry and not args.no_check:
        mark = _registered(args.registry, gaussians, file)
        if mark is None:
            raise ValueError(f"registry {args.registry} holds no mark of {model} (by its hash): pass --message/--key, "
                             "or --no-check")
        # the secret stays here: only the mark's id and label are printed
        message, bits, source = mark.message_hex, mark.num_bits, f"registry mark {mark.id} ({mark.label})"
    with output_file(output, [model], args.force) as tmp:
        save_model(gaussians, tmp, fmt)
    result: dict[str, Any] = {"input": str(model), "output": str(output), "format": fmt,
                              "gaussians": len(gaussians), "bytes": output.stat().st_size}
    if message is not None:
        views, kind = _check_views(gaussians, cameras, args.views, args.size)
        recorded = mark.background if mark is not None and mark.background is not None else (0.0, 0.0, 0.0)
        bg = (1.0, 1.0, 1.0) if args.white else tuple(recorded)
        check = check_conversion(gaussians, load_model(output, fmt), views, message, num_bits=bits, background=bg)
        result["check"] = {"message_from": source, "views": len(views), "view_kind": kind,
                           "bit_accuracy_before": check.mean_before, "bit_accuracy_after": check.mean_after,
                           "drop_points": check.drop_points, "warning": check.dropped()}
    if args.json:
        json.dump(result, sys.stdout, indent=2)
        print()
    else:
        print(f"wrote {output} ({fmt}, {len(gaussians):,} Gaussians, {result['bytes']:,} bytes)")
        if "check" in result:
            c = result["check"]
            print(f"watermark ({c['message_from']}, {c['views']} {c['view_kind']} views): bit accuracy "
                  f"{100 * c['bit_accuracy_before']:.2f} % before, {100 * c['bit_accuracy_after']:.2f} % after")
        elif not args.no_check:
            print("no watermark message (--message/--key, --registry or watermark.json): bit-accuracy check "
                  "skipped")
    if "check" in result and result["check"]["warning"]:
        print(f"gsw export: warning: the conversion to {fmt} lowered the watermark's bit accuracy by "
              f"{result['check']['drop_points']:.2f} points", file=sys.stderr)
    return 0
