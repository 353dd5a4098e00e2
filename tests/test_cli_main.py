"""The gsw command: every command registered, --version, and the one error path (one line, exit 2; --debug)."""

from __future__ import annotations

import pytest

import gsw
from gsw.cli.main import build_parser, main


def test_every_command_is_registered() -> None:
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert set(sub.choices) >= {"demo", "embed", "embed-image", "extract", "verify", "eval", "eval-grid", "train",
                                "render", "info"}


def test_version(capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"gsw {gsw.__version__}"


def test_expected_errors_are_one_line_naming_the_file(tmp_path, capsys) -> None:
    missing = tmp_path / "nope.png"
    assert main(["extract", str(missing)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gsw extract: error: ") and str(missing) in err and err.count("\n") == 1
    bad = tmp_path / "cameras.json"
    bad.write_text("[{")
    (tmp_path / "model.ply").write_bytes(b"")
    assert main(["embed", str(tmp_path / "model.ply"), "--cameras", str(bad), "--output", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gsw embed: error: ") and str(bad) in err and "JSON" in err and err.count("\n") == 1
    assert not (tmp_path / "o").exists()


def test_debug_shows_the_traceback(tmp_path) -> None:
    with pytest.raises(OSError):
        main(["--debug", "extract", str(tmp_path / "nope.png")])


def test_info(capsys) -> None:
    import json

    assert main(["info"]) == 0
    assert json.loads(capsys.readouterr().out)["version"] == gsw.__version__
