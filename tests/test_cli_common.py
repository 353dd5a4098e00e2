"""gsw.cli.common: the one message rule of --message / --key / --bits, backgrounds, safe output folders."""

from __future__ import annotations

import argparse

import pytest
import torch

from gsw.cli.common import add_background_options, add_message_options, background_of, message_from_args, \
    output_folder
from gsw.mark.message import message_from_hex, message_from_key


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_message_options(parser, claim=True)
    add_background_options(parser, "default: black")
    return parser.parse_args(list(argv))


def test_hex_message_length_is_inferred_and_checked() -> None:
    bits, n = message_from_args(_args("--message", "0123456789abcdef"), required=True)
    assert n == 64 and torch.equal(bits, message_from_hex("0123456789abcdef", 64))
    assert message_from_args(_args("--message", "0x0123abcd"), required=True)[1] == 32
    assert message_from_args(_args("--message", "0123abcd", "--bits", "32"), required=True)[1] == 32
    with pytest.raises(ValueError, match="--bits"):  # 40 bits: no decoder; the error names the way out
        message_from_args(_args("--message", "0123abcd01"), required=True)
    with pytest.raises(ValueError, match="64-bit message needs exactly 16 hex digits"):
        message_from_args(_args("--message", "0123abcd", "--bits", "64"), required=True)
    # a model's recorded length: used for keys, checked against a hex message
    assert message_from_args(_args("--key", "k"), required=True, stored_bits=48)[1] == 48
    with pytest.raises(ValueError, match="watermark.json"):
        message_from_args(_args("--message", "0123abcd"), required=True, stored_bits=48)


def test_key_becomes_a_message_once() -> None:
    bits, n = message_from_args(_args("--key", "studio", "--bits", "48"), required=True)
    assert n == 48 and torch.equal(bits, message_from_key("studio", 48))
    assert message_from_args(_args("--key", "studio"), required=True)[1] == 32  # the default length


@pytest.mark.parametrize("argv, required, match", [
    (("--message", "0123abcd", "--key", "k"), False, "not both"),
    (("--key", ""), False, "--key is empty"),
    (("--message", ""), False, "--message is empty"),
    ((), True, "pass --message HEX or --key SECRET"),
])
def test_bad_message_options(argv, required, match) -> None:
    with pytest.raises(ValueError, match=match):
        message_from_args(_args(*argv), required=required)


def test_no_message_means_random_only_where_allowed() -> None:
    assert message_from_args(_args(), required=False) == (None, 32)
    assert message_from_args(_args("--bits", "64"), required=False) == (None, 64)


def test_background_override_and_stored_default() -> None:
    assert background_of(_args()) == (0.0, 0.0, 0.0)
    assert background_of(_args(), (1.0, 1.0, 1.0)) == (1.0, 1.0, 1.0)
    assert background_of(_args("--black"), (1.0, 1.0, 1.0)) == (0.0, 0.0, 0.0)
    assert background_of(_args("--white")) == (1.0, 1.0, 1.0)


def test_output_folder_replaces_only_on_success(tmp_path) -> None:
    out = tmp_path / "out"
    with output_folder(out, [tmp_path / "input"], force=False) as tmp:
        (tmp / "a.txt").write_text("first")
    assert (out / "a.txt").read_text() == "first"
    with pytest.raises(ValueError, match="exists"):
        with output_folder(out, [], force=False):
            pass
    with pytest.raises(KeyError):
        with output_folder(out, [], force=True) as tmp:
            (tmp / "a.txt").write_text("second")
            raise KeyError("interrupted")
    assert (out / "a.txt").read_text() == "first"  # the old output survives a failed run
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temporary left
    with pytest.raises(ValueError, match="overlaps the input"):
        with output_folder(tmp_path / "in" / "sub", [tmp_path / "in"], force=True):
            pass


def test_readout_decoder_wraps_the_shipped_or_a_custom_decoder() -> None:
    import gsw
    from gsw.cli.common import READOUTS, add_readout_option, readout_decoder
    from gsw.registry import mark_decoder_sha256
    from gsw.decoder import KleinReadout
    from gsw.decoder.readout import shipped_klein_fingerprint
    from gsw.registry import shipped_decoder_sha256

    parser = argparse.ArgumentParser()
    add_readout_option(parser)
    assert parser.parse_args([]).readout == "direct" and READOUTS == ("direct", "klein")
    assert readout_decoder("direct", 32) is None  # the callee loads the shipped decoder, as without --readout
    assert mark_decoder_sha256(32, None) == shipped_decoder_sha256(32)
    shipped = readout_decoder("klein", 48)
    assert isinstance(shipped, KleinReadout) and shipped.num_bits == 48
    assert mark_decoder_sha256(48, shipped) == shipped_klein_fingerprint(48)  # what identify / scan recognise
    # any decoder module is wrapped, not only a shipped one
    custom = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3), torch.nn.AdaptiveAvgPool2d(1), torch.nn.Flatten(),
                                 torch.nn.Linear(4, 32))
    assert readout_decoder("direct", 32, custom) is custom
    klein = readout_decoder("klein", 32, custom)
    assert isinstance(klein, KleinReadout) and klein.inner is custom
    assert mark_decoder_sha256(32, klein) not in (shipped_klein_fingerprint(32), shipped_decoder_sha256(32))
    image = torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(0))
    assert gsw.extract(image, num_bits=32, decoder=klein).bits.shape == (1, 32)
    with pytest.raises(ValueError, match="--readout must be one of direct, klein"):
        readout_decoder("fancy", 32)
