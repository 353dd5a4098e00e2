"""Shared pieces of the `gsw` commands: option groups (message, device, background), the one place that turns
``--message`` / ``--key`` / ``--bits`` into a message, safe output files and folders, JSON output.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Sequence

from gsw.decoder.zoo import AVAILABLE_BITS

if TYPE_CHECKING:
    from torch import Tensor

#: Message length when neither ``--bits``, a hex message nor a model's ``watermark.json`` says otherwise.
DEFAULT_BITS = 32
#: Backgrounds of ``--white`` / ``--black``.
BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}


def positive_int(text: str) -> int:
    """argparse type: an integer > 0."""
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def print_json(data: Any) -> None:
    """Writes ``data`` to stdout as indented JSON (the only output of a command run with ``--json``)."""
    json.dump(data, sys.stdout, indent=2)
    print()


# ------------------------------------------------------------------------------------------------ options


def add_bits_option(parser: argparse._ActionsContainer, default: int | None, help_text: str) -> None:
    """``--bits 32|48|64``: the message length."""
    parser.add_argument("--bits", type=positive_int, choices=AVAILABLE_BITS, default=default, help=help_text)


def add_message_options(parser: argparse.ArgumentParser, *, claim: bool,
                        default_help: str = "a fresh secret message, printed once") -> None:
    """``--message HEX``, ``--key SECRET`` and ``--bits``: the message to embed (``claim=False``) or to test for.

    Turn them into a message with :func:`message_from_args`; ``default_help`` describes the message used
    when neither is given (embedding only).
    """
    group = parser.add_argument_group("message (--message or --key)")
    if claim:
        group.add_argument("--message", metavar="HEX", help="the embedded message, in hex")
        group.add_argument("--key", metavar="SECRET", help="the secret key the message was derived from")
    else:
        group.add_argument("--message", metavar="HEX", help=f"hex message (default: {default_help})")
        group.add_argument("--key", metavar="SECRET", help="derive the message from a secret key")
    source = "the hex message, the model's watermark.json" if claim else "the hex message"
    add_bits_option(group, None, f"message length (default: from {source}, else {DEFAULT_BITS})")


def message_from_args(args: argparse.Namespace, *, required: bool,
                      stored_bits: int | None = None) -> tuple[Tensor | None, int]:
    """The message of ``--message`` / ``--key`` / ``--bits`` and its length: the one place the CLI makes a message.

    The length is ``--bits`` when given, else the hex message's (4 bits per digit), else ``stored_bits`` (a model's
    ``watermark.json``), else :data:`DEFAULT_BITS`.

    Args:
        args: parsed arguments with ``message``, ``key`` and ``bits``.
        required: a message must be given (verification); otherwise None stands for "random".
        stored_bits: the message length recorded with a model, if any.

    Returns:
        ``([bits] 0/1 float tensor or None, number of bits)``.

    Raises:
        ValueError: both ``--message`` and ``--key``, an empty one, none when ``required``, a hex length that no
            decoder reads, or a length that contradicts ``--bits`` / ``stored_bits``.
    """
    from gsw.mark.detect import message_num_bits
    from gsw.mark.message import as_message, message_from_key

    hex_message, key, bits = args.message, args.key, args.bits
    if hex_message is not None and key is not None:
        raise ValueError("pass --message or --key, not both")
    if key == "" or hex_message == "":
        raise ValueError(f"--{'key' if key == '' else 'message'} is empty")
    if hex_message is None:
        if key is None and required:
            raise ValueError("pass --message HEX or --key SECRET")
        num_bits = bits or stored_bits or DEFAULT_BITS
        return (None if key is None else message_from_key(key, num_bits)), num_bits
    inferred = message_num_bits(hex_message)
    if bits is None:
        if inferred not in AVAILABLE_BITS:
            raise ValueError(f"--message has {inferred // 4} hex digits ({inferred} bits); the decoders read "
                             f"{', '.join(map(str, AVAILABLE_BITS))} bits: pass that many hex digits, or --bits")
        if stored_bits is not None and inferred != stored_bits:
            raise ValueError(f"--message has {inferred} bits but the model was watermarked with {stored_bits} "
                             "(watermark.json); pass --bits to test another length")
        bits = inferred
    return as_message(hex_message, bits), bits


def add_device_option(parser: argparse.ArgumentParser, default: str = "auto") -> None:
    """``--device auto|cpu|cuda|cuda:N`` (resolved by :func:`gsw.device.resolve_device`)."""
    parser.add_argument("--device", default=default, metavar="auto|cpu|cuda|cuda:N",
                        help="where to compute (auto: CUDA when gsw was built with it and a GPU is visible, else the "
                             "CPU; default: %(default)s)")


def add_background_options(parser: argparse.ArgumentParser, default_help: str, default: str | None = None) -> None:
    """``--white`` / ``--black``: the background (``args.background``: ``"white"``, ``"black"`` or ``default``;
    None stands for "the model's, else black", see :func:`background_of`)."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--white", dest="background", action="store_const", const="white",
                       help=f"white background ({default_help})")
    group.add_argument("--black", dest="background", action="store_const", const="black",
                       help="black background")
    parser.set_defaults(background=default)


def background_of(args: argparse.Namespace, stored: Sequence[float] | None = None) -> tuple[float, float, float]:
    """RGB background: ``--white`` / ``--black``, else ``stored`` (a model's ``watermark.json``), else black."""
    if args.background is not None:
        return BACKGROUNDS[args.background]
    if stored is not None:
        r, g, b = (float(v) for v in stored)
        return r, g, b
    return BACKGROUNDS["black"]


# ------------------------------------------------------------------------------------------------ files


@contextmanager
def reading(path: str | Path) -> Iterator[None]:
    """Names ``path`` in the error when what is read inside the block is not valid JSON / text."""
    try:
        yield
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: invalid JSON ({err})") from None
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not UTF-8 text ({err})") from None


def check_output(output: Path, inputs: Sequence[Path], force: bool) -> None:
    """Refuses an output (file or folder) that is, holds or lies inside an input, or exists without ``force``."""
    out = output.resolve()
    for src in inputs:
        src = src.resolve()
        if out == src or out in src.parents or src in out.parents:
            raise ValueError(f"output {output} overlaps the input {src}; inputs are never overwritten")
    if out.exists() and not force:
        raise ValueError(f"output {output} exists; pass --force to replace it")


@contextmanager
def output_folder(output: Path, inputs: Sequence[Path], force: bool) -> Iterator[Path]:
    """Checks an output folder and yields a fresh temporary sibling to write into; on success the temporary
    folder replaces ``output`` (an old output is removed only then), on failure it is removed."""
    check_output(output, inputs, force)
    out = output.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        yield tmp
        if output.exists():
            old = output.with_name(f".{output.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            output.rename(old)
            tmp.rename(output)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(output)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def read_images(paths: Sequence[str | Path]) -> list[Tensor]:
    """[3, H, W] images in [0, 1] (an alpha channel is composited on black, as renders are)."""
    from gsw.data.images import read_image

    images = []
    for p in paths:
        img = read_image(p)
        if img.shape[0] == 4:
            img = img[:3] * img[3:]
        images.append(img)
    return images
