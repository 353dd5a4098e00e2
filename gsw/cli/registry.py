"""``gsw keys list|show`` (the registry of issued marks), ``gsw identify`` (who leaked this?) and the
``--label`` / ``--registry`` options with which ``gsw embed`` / ``gsw embed-image`` record the marks they issue.

Messages are secrets: no command prints one unless asked with ``--show-secret`` (an embedding without
``--label`` prints its new message once, since nothing else keeps it). Exit status of ``gsw identify``:
0 when a recipient is identified, 1 when nobody is, 2 on an error.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING, Any

from gsw.cli.common import REGISTRY_HELP, positive_int
from gsw.stats import DETECTION_FPR

if TYPE_CHECKING:
    from torch import nn

__all__ = ["register", "cmd_keys_list", "cmd_keys_show", "cmd_identify", "add_record_options", "check_record",
           "record_issued", "issued_summary"]


def _open(args: argparse.Namespace):
    from gsw.registry import open_registry

    return open_registry(args.registry, create=False)


def _print_json(obj: Any) -> None:
    json.dump(obj, sys.stdout, indent=2)
    print()


def _short(text: str | None, n: int = 12) -> str:
    return "-" if text is None else text[:n]


def _describe(mark, show_secret: bool) -> list[tuple[str, str]]:
    size = "-" if mark.width is None else f"{mark.width}x{mark.height}"
    bg = "-" if mark.background is None else ", ".join(f"{v:g}" for v in mark.background)
    rows = [("id", str(mark.id)), ("label", mark.label), ("bits", str(mark.num_bits)),
            ("decoder sha256", mark.decoder_sha256), ("model hash", mark.model_hash or "-"),
            ("resolution", size), ("background", bg), ("created (UTC)", mark.created),
            ("gsw version", mark.gsw_version), ("message origin", mark.origin)]
    if show_secret:
        rows.insert(3, ("message", mark.message_hex))
    return rows


# ------------------------------------------------------------------------------------------------ recording


def add_record_options(parser: argparse.ArgumentParser) -> None:
    """``--label NAME`` and ``--registry FILE`` of the embedding commands: record the issued mark."""
    group = parser.add_argument_group("registry (record the issued mark; see `gsw keys`, `gsw identify`)")
    group.add_argument("--label", metavar="NAME",
                       help="record the mark under this recipient label in the registry (the message is then kept "
                            "there and not printed)")
    group.add_argument("--registry", metavar="FILE", help=REGISTRY_HELP + "; needs --label")


def check_record(args: argparse.Namespace, message, num_bits: int, decoder: nn.Module | None = None) -> None:
    """Before embedding (a long job): ``--registry`` needs ``--label``; the registry opens (it is created
    if missing) and holds neither the label nor, for a given message, that message read by ``decoder``
    (:func:`gsw.registry.mark_decoder_sha256`; None: the shipped one).

    Raises:
        ValueError, RegistryError: with what is wrong; nothing is embedded then.
    """
    from gsw.mark.message import message_to_hex
    from gsw.registry import UnknownMarkError, _check_label, mark_decoder_sha256, open_registry

    if args.label is None:
        if args.registry is not None:
            raise ValueError("--registry records the issued mark: pass --label NAME (the recipient) too")
        return
    label = _check_label(args.label)
    with open_registry(args.registry) as reg:
        try:
            reg.get(label)
        except UnknownMarkError:
            pass
        else:
            raise ValueError(f"label {label!r} is already registered in {reg.path}; choose another")
        if message is not None:
            text, sha = message_to_hex(message), mark_decoder_sha256(num_bits, decoder)
            if any(m.message_hex == text and m.decoder_sha256 == sha for m in reg.list(num_bits=num_bits)):
                raise ValueError(f"this message is already issued in {reg.path} (two recipients would be "
                                 "indistinguishable); use another --message/--key, or none")


def record_issued(args: argparse.Namespace, message, decoder: nn.Module | None = None, **fields: Any):
    """Records the issued mark when ``--label`` was given (:func:`gsw.registry.record_mark`, under
    :func:`gsw.registry.mark_decoder_sha256` of ``decoder``, the embedding's; ``fields``: its ``gaussians``, ``size``,
    ``background``, ``origin``). Returns ``(mark, registry path)`` or None."""
    from gsw.mark.detect import message_num_bits
    from gsw.registry import default_registry_path, mark_decoder_sha256, record_mark

    if args.label is None:
        return None
    num_bits = message_num_bits(message)
    mark = record_mark(args.registry, args.label, message, num_bits=num_bits,
                       decoder_sha256=mark_decoder_sha256(num_bits, decoder), **fields)
    return mark, args.registry or str(default_registry_path())


def issued_summary(recorded, message_hex: str, bits: list[int]) -> tuple[dict[str, Any], str]:
    """(JSON fields, text) that show a newly issued message once: the message itself (keep it: no output
    file stores it), or, when recorded, where the registry keeps it."""
    if recorded is None:
        return (dict(message=message_hex, bits=bits),
                f"message {message_hex} (secret: keep it; no output file stores it)")
    mark, path = recorded
    return (dict(mark=mark.to_dict(), registry=str(path)),
            f"message recorded as mark {mark.id} for {mark.label!r} in {path} "
            f"(see it with: gsw keys show {mark.id} --registry {path} --show-secret)")


def cmd_keys_list(args: argparse.Namespace) -> int:
    """Lists the registered marks (messages only with --show-secret)."""
    with _open(args) as reg:
        marks = reg.list()
    if args.json:
        _print_json([m.to_dict(args.show_secret) for m in marks])
        return 0
    header = ["id", "label", "bits", "decoder", "model", "created (UTC)"] + (["message"] if args.show_secret else [])
    rows = [[str(m.id), m.label, str(m.num_bits), _short(m.decoder_sha256), _short(m.model_hash, 20), m.created]
            + ([m.message_hex] if args.show_secret else []) for m in marks]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    for r in [header, *rows]:
        print("  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip())
    print(f"{len(marks)} mark{'s' * (len(marks) != 1)} in {reg.path}")
    return 0


def cmd_keys_show(args: argparse.Namespace) -> int:
    """Shows one mark by id or label (its message only with --show-secret)."""
    with _open(args) as reg:
        mark = reg.get(args.mark)
    if args.json:
        _print_json(mark.to_dict(args.show_secret))
        return 0
    rows = _describe(mark, args.show_secret)
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k:<{width}}  {v}")
    return 0


def cmd_identify(args: argparse.Namespace) -> int:
    """Tests images or video frames against every registered mark; exit 0 when someone is identified."""
    from gsw.io.video import load_named_images_or_video
    from gsw.mark.identify import identify

    if not 0.0 < args.fpr < 1.0:
        raise ValueError(f"--fpr must lie in (0, 1), got {args.fpr}")
    with _open(args) as reg:
        marks = reg.list()
        path = reg.path
    if not marks:
        raise ValueError(f"registry {path} holds no marks")
    named = load_named_images_or_video(args.inputs, args.frames, every=args.every)
    result = identify([img for _, img in named], marks, fpr=args.fpr, device=_device(args.device))
    if not result.results:
        shas = sorted({m.decoder_sha256[:12] for m in result.skipped})
        raise ValueError(f"none of the {len(marks)} registered marks can be tested: their decoders "
                         f"({', '.join(shas)}) are not the shipped ones")
    if args.json:
        out = result.to_dict(args.show_secret)
        out["images"] = [name for name, _ in named]
        _print_json(out)
    else:
        _print_identification(result, len(named), args.top)
    return 0 if result.identified else 1


def _device(name: str) -> str | None:
    """None (decode where the images are: the CPU) or a usable CUDA device."""
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else None
    if name == "cpu":
        return None
    if not name.startswith("cuda"):
        raise ValueError(f"--device must be auto, cpu or cuda[:N], got {name!r}")
    if not torch.cuda.is_available():
        raise ValueError(f"--device {name}: no CUDA device is available")
    return name


def _print_identification(result, num_images: int, top: int) -> None:
    tested = len(result.results)
    print(f"tested {tested} mark{'s' * (tested != 1)} on {num_images} image{'s' * (num_images != 1)} "
          f"(family-wise false-positive rate {result.fpr:g}, Holm)")
    if result.skipped:
        print(f"skipped {len(result.skipped)} mark(s) whose decoder is not available: "
              f"{', '.join(m.label for m in result.skipped[:5])}{' ...' if len(result.skipped) > 5 else ''}")
    for r in result.results[:max(top, len(result.identified))]:
        verdict = "IDENTIFIED" if r.identified else "          "
        print(f"{verdict}  {r.mark.label}  (id {r.mark.id}, {r.mark.num_bits} bits): adjusted p "
              f"{'=' if r.exact else '>='} {r.adjusted_p_value:.2e}, best image {100 * r.best_bit_accuracy:.1f} % "
              "of the bits")
    if result.identified:
        print(f"identified: {', '.join(result.recipients)}")
    else:
        print("nobody identified")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Adds ``keys`` (``list``, ``show``) and ``identify`` to the ``gsw`` command's subparsers."""
    keys = subparsers.add_parser("keys", help="the registry of issued marks (list, show)",
                                 description="The registry of issued marks: which recipient got which message. "
                                 "Messages are secret and printed only with --show-secret.")
    keys_sub = keys.add_subparsers(dest="keys_command", required=True)
    lst = keys_sub.add_parser("list", help="list the registered marks")
    lst.set_defaults(func=cmd_keys_list)
    show = keys_sub.add_parser("show", help="show one mark")
    show.add_argument("mark", help="the mark's id or recipient label")
    show.set_defaults(func=cmd_keys_show)
    for p in (lst, show):
        p.add_argument("--registry", help=REGISTRY_HELP)
        p.add_argument("--json", action="store_true", help="print JSON only")
        p.add_argument("--show-secret", action="store_true", help="also print the secret messages")

    idf = subparsers.add_parser("identify", help="name the recipient whose mark images or a video carry "
                                "(exit 0 = identified, 1 = nobody)",
                                description="Decodes the images (or frames of videos) once and tests every "
                                "registered mark; a recipient is identified when the Holm-adjusted p-value over "
                                "all registered marks is at most --fpr.")
    idf.add_argument("inputs", nargs="+", metavar="IMAGE|VIDEO|FOLDER", help="image files, video files (.mp4, "
                     ".mkv, .webm, .mov, ...; videos need PyAV) and folders of them (searched recursively), taken "
                     "together as one source")
    idf.add_argument("--registry", help=REGISTRY_HELP)
    idf.add_argument("--frames", type=positive_int, default=16,
                     help="frames read per video, spread evenly (default %(default)s)")
    idf.add_argument("--every", type=positive_int, default=None,
                     help="read every K-th frame of a video instead of --frames")
    idf.add_argument("--fpr", type=float, default=DETECTION_FPR,
                     help="family-wise false-positive rate over all registered marks (default %(default)g)")
    idf.add_argument("--device", default="auto", help="where to decode: auto, cpu or cuda (default auto)")
    idf.add_argument("--top", type=int, default=3, help="candidates shown besides the identified (default 3)")
    idf.add_argument("--show-secret", action="store_true", help="include messages in --json output")
    idf.add_argument("--json", action="store_true", help="print JSON only")
    idf.set_defaults(func=cmd_identify)
