"""`gsw demo`: the built-in scene watermarked and read back; --json prints JSON only."""

from __future__ import annotations

import json

from gsw.cli.main import main

TINY = ["--size", "48", "--views", "3", "--epochs", "1", "--lpips", "none", "--no-progress"]


def test_demo_json_is_pure_json(tmp_path, capsys) -> None:
    assert main(["demo", "--output", str(tmp_path / "demo"), "--message", "0123abcd", *TINY, "--json"]) == 0
    result = json.loads(capsys.readouterr().out)  # the whole output parses: no table, no banner
    assert result["message"] == "0123abcd" and result["num_bits"] == 32 and result["views"] == 3
    assert 0.0 <= result["bit_accuracy"] <= 1.0 and 0.0 <= result["p_value"] <= 1.0
    assert result["psnr"] > 0 and result["lpips"] is None
    assert 0 <= result["detected_views"] <= 3 and result["gaussians_out"] > 0
    for name in ("original.png", "watermarked.png", "difference_x2.png"):
        assert str(tmp_path / "demo" / name) in result["images"] and (tmp_path / "demo" / name).is_file()


def test_demo_table(tmp_path, capsys) -> None:
    assert main(["demo", "--output", str(tmp_path / "demo"), "--key", "k", "--bits", "48", *TINY]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert "48-bit message" in lines[0] and any(line.startswith("PSNR vs original render") for line in lines)
    assert [line.split()[-1] for line in lines if line.startswith("LPIPS")] == ["off"]
    assert "{" not in out


def test_demo_default_message_is_the_public_seeded_one(tmp_path, capsys) -> None:
    from gsw.mark.message import message_to_hex, random_message

    assert main(["demo", "--output", str(tmp_path / "demo"), "--seed", "3", *TINY, "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["message"] == message_to_hex(random_message(32, seed=3))  # reproducible: `make demo`
