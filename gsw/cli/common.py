"""Shared pieces of the `gsw` commands: option groups (message, device, background, readout), the one place that
turns ``--message`` / ``--key`` / ``--bits`` into a message, the one place that picks the decoder of ``--readout``,
safe output files and folders, JSON output.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Sequence

from gsw.decoder.zoo import AVAILABLE_BITS

if TYPE_CHECKING:
    from torch import Tensor, nn

#: Message length when neither ``--bits``, a hex message nor a model's ``watermark.json`` says otherwise.
DEFAULT_BITS = 32
#: Help text of every ``--registry`` option.
REGISTRY_HELP = ("registry file (default: $GSW_REGISTRY, else $XDG_DATA_HOME/gsw/registry.sqlite, "
                 "i.e. ~/.local/share/gsw/registry.sqlite)")
#: Backgrounds of ``--white`` / ``--black``.
BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}
#: Choices of ``--readout``: the decoder read as it is, or through :class:`gsw.decoder.KleinReadout`.
READOUTS = ("direct", "klein")


def positive_int(text: str) -> int:
    """argparse type: an integer > 0."""
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _finite_float(text: str, zero_allowed: bool) -> float:
    """``text`` as a finite number > 0 (>= 0 with ``zero_allowed``), or an argparse error saying which."""
    value = float(text)
    if not (value >= 0 if zero_allowed else value > 0) or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be {'a number >= 0' if zero_allowed else 'a positive number'}, "
                                         f"got {text}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    return _finite_float(text, zero_allowed=False)


def non_negative_float(text: str) -> float:
    """argparse type: a finite number >= 0."""
    return _finite_float(text, zero_allowed=True)


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


def add_readout_option(parser: argparse._ActionsContainer) -> None:
    """``--readout direct|klein`` (default direct): how the decoder is read; turn it into a decoder with
    :func:`readout_decoder`."""
    parser.add_argument("--readout", choices=READOUTS, default="direct",
                        help="klein: read the decoder through flips that cancel its per-bit bias (fair per bit on "
                             "unmarked images), at four decoder passes; a mark must be read with the readout it was "
                             "embedded with (default: %(default)s)")


def check_readout_origin(readout: str, origin: str, num_bits: int) -> None:
    """A chosen message is issued or verified through ``--readout klein`` only where a null model calibrated
    through that readout ships for ``num_bits`` (``gsw/decoder/weights/null_k{bits}_klein.json``).

    Without one it would be tested against the fair coin, and on held-out unmarked photos that test passes messages
    aligned with the decoder's lean 3.6 % of the time at the nominal 1 % (``benchmarks/klein_chosen_fp.py``,
    BENCHMARKS.md). Random messages (``--key``, or none) are tested exactly through any readout.

    Raises:
        ValueError: ``readout`` is ``klein``, ``origin`` is ``chosen`` and no such null model ships.
    """
    if readout != "klein" or origin != "chosen":
        return
    from gsw.decoder.null import NullModelError
    from gsw.mark.evidence import shipped_null_model

    try:
        shipped_null_model(num_bits, "klein")
    except NullModelError:
        raise ValueError(f"a chosen message (--message HEX, --chosen-message, or a model embedded with one) has no "
                         f"valid test through --readout klein at {num_bits} bits: no null model calibrated through "
                         "that readout ships for this length, and the fair coin passes messages aligned with the "
                         "decoder's lean 3.6 % of the time at the nominal 1 % on unmarked photos (BENCHMARKS.md); use "
                         "--key SECRET or no message (random messages are tested exactly), or --readout direct"
                         ) from None


def readout_decoder(readout: str, num_bits: int, decoder: nn.Module | None = None) -> nn.Module | None:
    """The ``decoder=`` that ``gsw.embed`` / ``gsw.embed_images`` / ``gsw.extract`` / ``gsw.verify`` get for a
    ``--readout`` choice: the one place the CLI picks its decoder.

    Args:
        readout: one of :data:`READOUTS`.
        num_bits: message length (selects the shipped decoder).
        decoder: a decoder to read instead of the shipped one (any module LL2 subband -> logits); None: the
            shipped ``num_bits`` decoder.

    Returns:
        ``direct``: ``decoder`` as given (None: the callee loads the shipped one, as without ``--readout``);
        ``klein``: :class:`gsw.decoder.KleinReadout` over ``decoder``, else over the shipped decoder.

    Raises:
        ValueError: an unknown readout.
        WeightsError: ``klein`` without ``decoder`` and no shipped decoder of ``num_bits``.
    """
    if readout not in READOUTS:
        raise ValueError(f"--readout must be one of {', '.join(READOUTS)}, got {readout!r}")
    if readout == "direct":
        return decoder
    from gsw.decoder.readout import KleinReadout
    from gsw.decoder.zoo import load_decoder

    return KleinReadout(load_decoder(num_bits) if decoder is None else decoder)


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


def input_paths(args: argparse.Namespace, *names: str) -> list[Path]:
    """The paths of the options ``names`` that were given (e.g. ``"input", "cameras", "images", "registry"``): the
    inputs that :func:`check_output` protects. Names the command does not have are skipped."""
    return [Path(v) for v in (getattr(args, n, None) for n in names) if v is not None and not isinstance(v, bool)]


def check_output(output: Path, inputs: Sequence[Path], force: bool) -> None:
    """Refuses an output (file or folder) that is, holds or lies inside an input (``force`` or not), or exists
    without ``force``."""
    out = output.resolve()
    for src in inputs:
        src = Path(src).resolve()
        if out == src or out in src.parents or src in out.parents:
            raise ValueError(f"output {output} overlaps the input {src}; inputs are never overwritten, "
                             "--force or not")
    if (out.exists() or output.is_symlink()) and not force:
        raise ValueError(f"output {output} exists; pass --force to replace it")


@contextmanager
def output_folder(output: Path, inputs: Sequence[Path], force: bool) -> Iterator[Path]:
    """Checks an output folder (:func:`check_output`) and yields a new temporary sibling to write into.

    On success the temporary folder becomes ``output`` (:func:`gsw._atomic.atomic_output`): an output that appeared
    meanwhile is refused without ``force`` (exclusive creation), an old one is replaced only then; on a failure or
    SIGINT / SIGTERM the temporary folder is removed.
    """
    from gsw._atomic import atomic_output

    check_output(output, inputs, force)
    with atomic_output(output, folder=True, replace=force) as tmp:
        yield tmp


@contextmanager
def output_file(output: Path, inputs: Sequence[Path], force: bool) -> Iterator[Path]:
    """:func:`output_folder` for one file: yields a temporary path beside ``output`` for the block to write."""
    from gsw._atomic import atomic_output

    check_output(output, inputs, force)
    with atomic_output(output, folder=False, replace=force) as tmp:
        yield tmp


def claim_output_folder(output: Path, inputs: Sequence[Path], force: bool) -> Path:
    """Creates a new output folder at once (for long jobs that write checkpoints into it as they go).

    The folder is created exclusively (a concurrent run gets :class:`FileExistsError`); with ``force`` an old
    output is first moved aside under a temporary name and removed. Files written into it should be atomic
    (:func:`gsw._atomic.atomic_write`); on a failure the partial folder is kept (its checkpoints are results).
    """
    from gsw._atomic import remove_path, sweep_stale, temp_path

    check_output(output, inputs, force)
    parent = output.resolve().parent
    parent.mkdir(parents=True, exist_ok=True)
    sweep_stale(parent)
    if force and (output.exists() or output.is_symlink()):
        aside = temp_path(output)  # a gsw temporary name: swept by a later run if this one dies here
        os.rename(output, aside)
        remove_path(aside)
    try:
        os.mkdir(output, 0o777)
    except FileExistsError:
        raise FileExistsError(f"output {output} appeared after this run started (another run?); pass --force "
                              "to replace it") from None
    return output


def not_detectable_warning(command: str, fpr: float, what: Sequence[str], hint: str) -> None:
    """The one wording of "the output does not carry a detectable mark" (stderr; the command then exits 1)."""
    print(f"gsw {command}: warning: not detectable at p <= {fpr:g}: {', '.join(what)} ({hint})", file=sys.stderr)


def add_mse_option(parser: argparse._ActionsContainer) -> None:
    """``--mse W``: the squared-error image term's weight (``LossWeights(l1=0, mse=W)``); 0: the paper's L1 term."""
    parser.add_argument("--mse", type=non_negative_float, default=None, metavar="W",
                        help="the image term of the loss: W x the mean squared error, the error PSNR measures "
                             "(35 pulls as hard as L1 near 37 dB), or with 0 the paper's L1 term; default: the "
                             "recipe's (35 for gsw embed's default recipe: +2.1 dB on lego 800x800 and +0.5 dB on "
                             "the built-in scene against L1, BENCHMARKS.md 9l / 9m; also gsw fingerprint's; L1 for "
                             "--recipe paper)")


def add_resize_images_option(parser: argparse.ArgumentParser) -> None:
    """``--resize-images``: the opt-in for INRIA ``--images`` folders of full-size photos."""
    parser.add_argument("--resize-images", action="store_true",
                        help="resample --images whose size is a uniform multiple of their camera's in cameras.json "
                             "(INRIA stores its training resolution there; full-size photos differ)")


def resized_notice(command: str, names: Sequence[str]) -> None:
    """Tells on stderr which ``--images`` were resampled to their camera's size (``--resize-images``)."""
    if names:
        shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
        print(f"gsw {command}: notice: --resize-images resampled {len(names)} image(s) to their camera's size in "
              f"cameras.json: {shown}", file=sys.stderr)


def split_views(num_views: int, every: int) -> tuple[list[int], list[int], bool]:
    """The views to embed with and the views to verify the output on.

    Every ``every``-th view is held out of the embedding when there are at least ``every`` views (``every >= 2``);
    otherwise the output is verified on the embedding views themselves.

    Returns:
        ``(embedding indices, verification indices, whether the verification views are held out)``.
    """
    if every >= 2 and num_views >= every:
        from gsw.data.loaders import holdout_indices

        train, test = holdout_indices(num_views, every)
        return train, test, True
    every_view = list(range(num_views))
    return every_view, every_view, False


def verify_written_model(folder: Path, cameras: Sequence[Any], checked: Sequence[int], held_out: bool,
                         message: Tensor, *, num_bits: int, background: Sequence[float], fpr: float,
                         device: Any, origin: str = "random", decoder: nn.Module | None = None) -> dict[str, Any]:
    """Reads a written INRIA model folder back and tests it for ``message`` on the views ``checked`` (the
    calibrated :func:`gsw.mark.detect.verify`, at the common size of ``cameras`` when they share one).

    Args:
        folder: the written model folder.
        cameras: all its cameras (the embedding resolution is their common size).
        checked: indices of the verification views; ``held_out`` tells whether the embedding skipped them.
        message: [k] the embedded bits.
        num_bits: k.
        background: RGB render background of the embedding.
        fpr: false-positive rate of the decision.
        device: where to render.
        origin: the message's origin (``"random"`` or ``"chosen"``, :func:`gsw.mark.detect.verify`).
        decoder: the decoder the mark was embedded for (:func:`readout_decoder`); None: the shipped one.

    Returns:
        JSON-able ``views, held_out, where`` (a phrase), ``bit_accuracy`` (mean), ``p_value``, ``fpr``, ``detected``.
    """
    from gsw.data import load_inria_model
    from gsw.mark.detect import verify

    model = load_inria_model(folder)
    sizes = {(c.height, c.width) for c in cameras}
    r, g, b = (float(v) for v in background)
    v = verify((model.gaussians.to(device), [cameras[i] for i in checked]), message, num_bits=num_bits,
               decoder=decoder, background=(r, g, b), embed_size=next(iter(sizes)) if len(sizes) == 1 else None,
               origin=origin)
    where = (f"{len(checked)} held-out view(s) (cameras not used for embedding)" if held_out else
             f"the {len(checked)} embedding view(s) (fewer than --holdout-every cameras: none held out)")
    return dict(views=[cameras[i].name or f"view {i}" for i in checked], held_out=held_out, where=where,
                bit_accuracy=sum(v.bit_accuracy) / len(checked), p_value=v.p_value, fpr=fpr,
                detected=v.detected(fpr))


