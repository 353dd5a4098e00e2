"""The `gsw export` command: conversions, output safety, and the watermark check."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from gsw.cli.main import main
from gsw.data import save_inria_model
from gsw.io import load_gaussians, model_format
from gsw.scenes import default_scene


def digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    scene = default_scene(width=32, height=32, n_cameras=3, detail=0.3)
    folder = tmp_path_factory.mktemp("model")
    save_inria_model(folder, scene.gaussians, scene.cameras, iteration=5)
    return folder


@pytest.mark.parametrize("name,fmt", [("m.spz", "spz"), ("m.compressed.ply", "compressed-ply"),
                                      ("m.splat", "splat"), ("m.ply", "ply")])
def test_exports_every_format_without_touching_the_input(model_dir, tmp_path, capsys, name, fmt):
    before = digest(model_dir)
    out = tmp_path / "sub" / name
    assert main(["export", str(model_dir), "--output", str(out), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["format"] == fmt and model_format(out) == fmt and "check" not in result
    g = load_gaussians(out)
    assert len(g) == result["gaussians"] and result["bytes"] == out.stat().st_size
    assert digest(model_dir) == before
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temporary left


def test_output_safety(model_dir, tmp_path, capsys):
    ply = next(model_dir.glob("point_cloud/*/point_cloud.ply"))
    before = digest(model_dir)
    assert main(["export", str(ply), "--output", str(ply), "--format", "ply"]) == 2  # never over the input
    assert main(["export", str(model_dir), "--output", str(model_dir / "x.spz")]) == 2  # nor inside it
    assert main(["export", str(ply), "--output", str(tmp_path / "a.spz"), "--format", "splat"]) == 2
    assert "does not match" in capsys.readouterr().err
    assert main(["export", str(ply), "--output", str(tmp_path / "a.obj")]) == 2
    assert "unknown model file extension" in capsys.readouterr().err
    assert main(["export", str(ply), "--output", str(tmp_path / "a.spz")]) == 0
    assert main(["export", str(ply), "--output", str(tmp_path / "a.spz")]) == 2  # exists
    assert main(["export", str(ply), "--output", str(tmp_path / "a.spz"), "--force"]) == 0
    assert digest(model_dir) == before


def test_watermark_check_reports_before_and_after(model_dir, tmp_path, capsys):
    out = tmp_path / "m.splat"
    rc = main(["export", str(model_dir), "--output", str(out), "--key", "secret", "--views", "2", "--json"])
    assert rc == 0
    captured = capsys.readouterr()
    check = json.loads(captured.out)["check"]
    assert check["message_from"] == "--key" and check["views"] == 2 and check["view_kind"] == "model cameras"
    for key in ("bit_accuracy_before", "bit_accuracy_after"):
        assert 0.0 <= check[key] <= 1.0
    assert check["drop_points"] == pytest.approx(100 * (check["bit_accuracy_before"] - check["bit_accuracy_after"]))
    assert check["warning"] == (check["drop_points"] > 1.0)
    assert ("warning" in captured.err) == check["warning"]
    # the message of the folder's watermark.json (written by gsw embed) is used when none is given
    marked = tmp_path / "marked"
    shutil.copytree(model_dir, marked)
    (marked / "watermark.json").write_text(json.dumps({"message": "0123abcd", "bits": [0] * 32}))
    assert main(["export", str(marked), "--output", str(tmp_path / "n.spz"), "--views", "1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["check"]["message_from"] == "watermark.json"
    # a bare model file has no cameras: orbit views
    ply = next(model_dir.glob("point_cloud/*/point_cloud.ply"))
    assert main(["export", str(ply), "--output", str(tmp_path / "o.spz"), "--message", "0123abcd", "--views", "1",
                 "--size", "32", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["check"]["view_kind"] == "orbit 32x32"
    assert main(["export", str(marked), "--output", str(tmp_path / "p.spz"), "--no-check"]) == 0
    out = capsys.readouterr().out
    assert "bit accuracy" not in out and "check skipped" not in out



def test_watermark_check_reads_the_registered_mark_of_the_model(model_dir, tmp_path, capsys):
    """With --registry, the mark registered for this very model (by its Gaussians' or its file's hash) gives the
    message and the background; the message is never printed; a registry without it is an error before writing."""
    from gsw.data import load_inria_model
    from gsw.registry import hash_gaussians, hash_model_file, open_registry, shipped_decoder_sha256

    g = load_inria_model(model_dir).gaussians
    ply = next(model_dir.glob("point_cloud/*/point_cloud.ply"))
    sha = shipped_decoder_sha256(32)
    reg = tmp_path / "marks.sqlite"
    with open_registry(reg) as r:
        r.add("other", "0f0f0f0f", decoder_sha256=sha, model_hash="sha256:" + "0" * 64)
        r.add("bob", "89abcdef", decoder_sha256=sha, model_hash=hash_gaussians(g), background=(1.0, 1.0, 1.0))
    views = ["--views", "2", "--json"]
    assert main(["export", str(model_dir), "--output", str(tmp_path / "a.splat"), "--registry", str(reg), *views]) == 0
    out = capsys.readouterr().out
    check = json.loads(out)["check"]
    assert check["message_from"] == "registry mark 2 (bob)" and "89abcdef" not in out
    assert main(["export", str(model_dir), "--output", str(tmp_path / "b.splat"), "--message", "89abcdef", "--white",
                 *views]) == 0
    given = json.loads(capsys.readouterr().out)["check"]
    assert (check["bit_accuracy_before"], check["bit_accuracy_after"]) == (given["bit_accuracy_before"],
                                                                           given["bit_accuracy_after"])
    # a mark recorded with the file's hash (gsw fingerprint's copies)
    by_file = tmp_path / "files.sqlite"
    with open_registry(by_file) as r:
        r.add("carol", "76543210", decoder_sha256=sha, model_hash=hash_model_file(ply))
    assert main(["export", str(ply), "--output", str(tmp_path / "c.spz"), "--registry", str(by_file), "--size", "32",
                 *views]) == 0
    assert json.loads(capsys.readouterr().out)["check"]["message_from"] == "registry mark 1 (carol)"
    empty = tmp_path / "empty.sqlite"
    open_registry(empty).close()
    assert main(["export", str(model_dir), "--output", str(tmp_path / "d.splat"), "--registry", str(empty)]) == 2
    assert "holds no mark of" in capsys.readouterr().err and not (tmp_path / "d.splat").exists()
