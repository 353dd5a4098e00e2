"""`gsw embed` checks its own output on held-out views (exit 1 when not detectable), `--resize-images` is the
explicit opt-in for full-size photos, every input (model, cameras, --images, registry) is safe from --output/--force,
and `gsw train` claims its output folder exclusively."""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
from pathlib import Path

import pytest
import torch

from gsw.cli.common import check_output, input_paths
from gsw.cli.main import main
from gsw.data import load_inria_model, save_inria_model, write_image
from gsw.mark import verify
from gsw.scenes import default_scene

SIZE = 32


def _sha256(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """An INRIA folder of 8 views at 32x32 with full-size photos (2x) in ``images/``."""
    scene = default_scene(width=SIZE, height=SIZE, n_cameras=8, detail=0.3, sh_degree=0)
    folder = tmp_path_factory.mktemp("model") / "m"
    save_inria_model(folder, scene.gaussians, scene.cameras, iteration=7)
    (folder / "images").mkdir()
    for k, cam in enumerate(scene.cameras):
        write_image(folder / "images" / f"{cam.name}.png", torch.full((3, 2 * SIZE, 2 * SIZE), k / 8))
    return folder


def _run(argv: list[str]) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(argv)
    return rc, out.getvalue()


def test_full_size_images_need_resize_images_and_the_error_names_it(model, tmp_path, capsys) -> None:
    before = _sha256(model)
    argv = ["embed", str(model), "--images", str(model / "images"), "--output", str(tmp_path / "o"),
            "--epochs", "1", "--lpips", "none", "--device", "cpu", "--no-progress"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("gsw embed: error: ") and "--resize-images" in err and "orbit_000.png" in err
    assert not (tmp_path / "o").exists() and _sha256(model) == before


def test_embed_exits_1_when_its_output_is_not_detectable_on_held_out_views(model, tmp_path, capsys) -> None:
    before = _sha256(model)
    out = tmp_path / "marked"
    rc, text = _run(["embed", str(model), "--images", str(model / "images"), "--resize-images", "--output", str(out),
                     "--key", "k", "--epochs", "1", "--message-weight", "0", "--holdout-every", "4", "--lpips",
                     "none", "--device", "cpu", "--no-progress", "--json"])
    err = capsys.readouterr().err
    assert rc == 1, err
    assert "notice: --resize-images resampled 8 image(s)" in err
    assert f"gsw embed: warning: not detectable at p <= 1e-06: {out}" in err and "2 held-out view(s)" in err
    report = json.loads(text)
    check = report["verification"]
    assert check["held_out"] is True and check["views"] == ["orbit_000", "orbit_004"]
    assert check["detected"] is False and check["fpr"] == 1e-6
    # the written model is kept and the check is the calibrated verification of the written file
    marked = load_inria_model(out)
    assert len(marked.cameras) == 8  # every camera is kept in the output
    expect = verify((marked.gaussians, [marked.cameras[0], marked.cameras[4]]), "key:k", num_bits=32,
                    embed_size=(SIZE, SIZE))
    assert check["p_value"] == pytest.approx(expect.p_value)
    assert _sha256(model) == before


@pytest.mark.parametrize("target", ["images", "cameras.json", "point_cloud", "."])
def test_force_never_reaches_an_input(model, tmp_path, capsys, target) -> None:
    before = _sha256(model)
    output = model / target
    assert main(["embed", str(model), "--images", str(model / "images"), "--output", str(output), "--force",
                 "--epochs", "1", "--device", "cpu", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "overlaps the input" in err and "--force or not" in err
    assert _sha256(model) == before
    # a .ply input with --cameras: both are inputs
    ply = next(model.glob("point_cloud/iteration_*/point_cloud.ply"))
    for output in (ply, model / "cameras.json"):
        assert main(["embed", str(ply), "--cameras", str(model / "cameras.json"), "--output", str(output),
                     "--force", "--device", "cpu", "--no-progress"]) == 2
    assert _sha256(model) == before


def test_input_paths_cover_every_input_option(tmp_path) -> None:
    args = argparse.Namespace(input="m", cameras=None, images="imgs", registry=str(tmp_path / "marks.sqlite"),
                              force=True)
    inputs = input_paths(args, "input", "cameras", "images", "registry", "not_an_option")
    assert inputs == [Path("m"), Path("imgs"), tmp_path / "marks.sqlite"]
    with pytest.raises(ValueError, match="marks.sqlite"):
        check_output(tmp_path / "marks.sqlite", inputs, force=True)
    with pytest.raises(ValueError, match="marks.sqlite"):
        check_output(tmp_path, inputs, force=True)  # a folder holding an input


def test_train_claims_its_output_and_takes_resize_images(model, tmp_path, capsys) -> None:
    before = _sha256(model)
    out = tmp_path / "trained"
    argv = ["train", str(model), "--images", str(model / "images"), "-o", str(out), "--iterations", "2",
            "--init-points", "50", "--no-eval", "--device", "cpu", "--no-progress"]
    assert main(argv) == 2
    assert "--resize-images" in capsys.readouterr().err and not out.exists()
    assert main([*argv, "--resize-images"]) == 0
    assert "notice: --resize-images resampled" in capsys.readouterr().err
    assert (out / "train_result.json").is_file()
    assert main([*argv, "--resize-images"]) == 2  # exists
    assert "--force" in capsys.readouterr().err
    (out / "stale.txt").write_text("from the old run")
    assert main([*argv, "--resize-images", "--force"]) == 0
    assert not (out / "stale.txt").exists() and (out / "train_result.json").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["trained"]  # nothing moved aside is left
    assert main([*argv, "--resize-images", "--force", "-o", str(model / "images")]) == 2
    assert _sha256(model) == before
