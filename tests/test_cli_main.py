"""The gsw command line: embed/extract/verify on an INRIA folder, demo, safety of outputs."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from gsw.cli.main import main
from gsw.data import save_inria_model
from gsw.scenes import default_scene


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    scene = default_scene(width=48, height=48, n_cameras=4, detail=0.4)
    folder = tmp_path_factory.mktemp("model")
    save_inria_model(folder, scene.gaussians, scene.cameras, iteration=100)
    return folder


def test_embed_writes_a_new_folder_and_never_touches_the_input(model_dir, tmp_path, capsys) -> None:
    before = _digest(model_dir)
    out = tmp_path / "marked"
    rc = main(["embed", str(model_dir), "--output", str(out), "--message", "0123abcd", "--epochs", "1",
               "--lpips", "none", "--white", "--no-progress", "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["message"] == "0123abcd"
    assert (out / "point_cloud" / "iteration_0" / "point_cloud.ply").is_file()
    assert (out / "cameras.json").is_file() and (out / "watermark.json").is_file()
    assert _digest(model_dir) == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left
    # refuses to overwrite an existing output, or to write into the input
    assert main(["embed", str(model_dir), "--output", str(out), "--epochs", "1", "--lpips", "none",
                 "--no-progress"]) == 2
    assert main(["embed", str(model_dir), "--output", str(model_dir / "sub"), "--epochs", "1",
                 "--lpips", "none", "--no-progress"]) == 2
    assert _digest(model_dir) == before
    # verify renders the model: exit status 0 only when detected
    rc = main(["verify", "--model", str(out), "--message", "0123abcd", "--fpr", "1.0", "--json"])
    assert rc == 0
    report = json.loads(capsys.readouterr().out)
    assert len(report["views"]) == 4 and 0.0 <= report["p_value"] <= 1.0


def test_extract_and_verify_images(model_dir, tmp_path, capsys) -> None:
    out = tmp_path / "renders"
    assert main(["render", str(model_dir / "point_cloud" / "iteration_100" / "point_cloud.ply"),
                 "--cameras", str(model_dir / "cameras.json"), "--output", str(out)]) == 0
    pngs = sorted(str(p) for p in out.glob("*.png"))
    assert len(pngs) == 4
    capsys.readouterr()
    assert main(["extract", *pngs, "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert len(rows) == 4 and all(len(r["hex"]) == 8 for r in rows)
    assert main(["verify", *pngs, "--message", rows[0]["hex"], "--fpr", "1e-6"]) in (0, 1)


def test_bad_cli_inputs(tmp_path, capsys) -> None:
    assert main(["embed", str(tmp_path / "missing"), "--output", str(tmp_path / "o")]) == 2
    assert main(["extract", str(tmp_path / "nope.png")]) == 2
    assert "error" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["embed", "x", "--output", "y", "--bits", "31"])


def test_demo_tiny(tmp_path, capsys) -> None:
    rc = main(["demo", "--output", str(tmp_path / "demo"), "--size", "48", "--views", "3", "--epochs", "1",
               "--lpips", "none", "--no-progress", "--json"])
    assert rc == 0
    out = capsys.readouterr().out
    table = json.loads(out[out.index("{"):])
    assert table["message"] and "dB" in table["PSNR vs original render"]
    for name in ("original.png", "watermarked.png", "difference_x2.png"):
        assert (tmp_path / "demo" / name).is_file()


def test_embed_robustness_flags_reach_the_config() -> None:
    from gsw.cli.main import _embed_config, build_parser
    from gsw.mark.loss import LossWeights

    args = build_parser().parse_args(["embed", "in", "--output", "out", "--attacks", "0.5",
                                      "--model-attack-prob", "0.5", "--message-weight", "0.1"])
    cfg = _embed_config(args)
    assert (cfg.attacks, cfg.model_attacks, cfg.weights.message) == (0.5, 0.5, 0.1)
    default = _embed_config(build_parser().parse_args(["embed", "in", "--output", "out"]))
    assert default.model_attacks == 0.0 and default.weights.message == LossWeights().message
