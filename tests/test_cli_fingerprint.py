"""`gsw fingerprint` and `gsw scan` on the command line (in one process: --local)."""

from __future__ import annotations

import csv
import json

import pytest
import torch

from gsw.cli.main import build_parser, main
from gsw.data import save_inria_model
from gsw.data.images import write_image
from gsw.registry import open_registry, shipped_decoder_sha256
from gsw.scenes import default_scene


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    scene = default_scene(width=32, height=32, n_cameras=2, detail=0.2)
    folder = tmp_path_factory.mktemp("model") / "m"
    save_inria_model(folder, scene.gaussians, scene.cameras, iteration=7)
    return folder


def _fingerprint(model_dir, tmp_path, csv_text: str, *extra: str) -> int:
    (tmp_path / "recipients.csv").write_text(csv_text, encoding="utf-8")
    return main(["fingerprint", str(model_dir), "--recipients", str(tmp_path / "recipients.csv"), "--output",
                 str(tmp_path / "out"), "--registry", str(tmp_path / "marks.sqlite"), "--local", "--epochs", "1",
                 "--lpips", "none", "--batch", "2", "--device", "cpu", "--no-progress", *extra])


def test_fingerprint_writes_registers_and_resumes(model_dir, tmp_path, capsys) -> None:
    assert _fingerprint(model_dir, tmp_path, "recipient,key\nalice,\nbob,bobs-key\n", "--json") == 0
    report = json.loads(capsys.readouterr().out)
    assert [r["status"] for r in report["recipients"]] == ["embedded", "embedded"] and report["runner"] == "local"
    assert 0 < report["timings"]["load"] and {"setup", "before_finetune", "finetune", "total"} <= set(report["timings"])
    assert (tmp_path / "out" / "bob" / "point_cloud" / "iteration_0" / "point_cloud.ply").is_file()
    with open_registry(tmp_path / "marks.sqlite") as reg:
        secrets = [m.message_hex for m in reg.list()]
    assert len(secrets) == 2 and not any(s in json.dumps(report) for s in secrets)
    assert _fingerprint(model_dir, tmp_path, "recipient,key\nalice,\nbob,bobs-key\ncarol,\n",
                        "--early-stop", "min_steps=1,window=1,margin=50") == 0
    captured = capsys.readouterr()
    out = captured.out
    assert "skipped alice" in out and "skipped bob" in out and "embedded carol" in out
    assert "2 steps" in out  # a margin no decoder reaches: carol runs to the cap (1 epoch of 2 views)
    assert "warning" not in captured.err  # no confirmation asked for: nothing to warn about
    unreachable = "min_steps=1,confirm=1,psnr_target=200"  # a confirmation no copy passes: dave gets a warning
    assert _fingerprint(model_dir, tmp_path, "recipient\ndave\n", "--early-stop", unreachable) == 0
    err = capsys.readouterr().err
    assert "warning: 1 of 1 copies reached the step cap" in err and "dave (" in err
    assert ">= 100 % bits, >= 200 dB" in err


def test_fingerprint_readout_klein_records_the_wrapper(model_dir, tmp_path, capsys) -> None:
    """`--readout klein` fingerprints through KleinReadout: the registry and the output folder record the wrapper's
    fingerprint (so `gsw identify` / `gsw scan` read the copies through it), and the copy's renders read the
    recipient's message through it as the job measured."""
    import gsw
    from gsw.data import load_inria_model
    from gsw.decoder import KleinReadout
    from gsw.decoder.readout import shipped_klein_fingerprint
    from gsw.decoder.zoo import load_decoder

    assert _fingerprint(model_dir, tmp_path, "recipient\nalice\n", "--readout", "klein", "--json") == 0
    row = json.loads(capsys.readouterr().out)["recipients"][0]
    with open_registry(tmp_path / "marks.sqlite") as reg:
        (mark,) = reg.list()
    assert mark.decoder_sha256 == shipped_klein_fingerprint(32) != shipped_decoder_sha256(32)
    copy = load_inria_model(tmp_path / "out" / "alice")
    renders = [gsw.rasterize(copy.gaussians, cam).image for cam in copy.cameras]
    read = gsw.extract(renders, num_bits=32, decoder=KleinReadout(load_decoder(32)), embed_size=(32, 32)).bits
    message = torch.tensor([int(c) for c in bin(int(mark.message_hex, 16))[2:].zfill(32)], dtype=read.dtype)
    assert float((read == message).float().mean()) == pytest.approx(row["bit_accuracy"], abs=1e-6)
    # Chosen messages (a recipients file's message column) of a length with no null model calibrated through the
    # readout (48 bits) have no valid test through it: refused.
    assert _fingerprint(model_dir, tmp_path, "recipient,message\ncarol,0123456789ab\n", "--readout", "klein",
                        "--bits", "48") == 2
    assert "no valid test through --readout klein at 48 bits" in capsys.readouterr().err
    # A stopping rule that may redraw drawn messages registers them as chosen: refused there too.
    assert _fingerprint(model_dir, tmp_path, "recipient\ndave\n", "--readout", "klein", "--bits", "48",
                        "--early-stop", "careful,redraw=1") == 2
    assert "no valid test through --readout klein at 48 bits" in capsys.readouterr().err
    # The same folder cannot take copies read through the direct readout.
    assert _fingerprint(model_dir, tmp_path, "recipient\nbob\n") == 2
    assert "another decoder" in capsys.readouterr().err


def test_bad_early_stop_setting(model_dir, tmp_path, capsys) -> None:
    assert _fingerprint(model_dir, tmp_path, "recipient\nalice\n", "--early-stop", "windw=4") == 2
    assert "early-stop setting 'windw=4'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_novel_views_reach_the_pool(model_dir, tmp_path, capsys, monkeypatch) -> None:
    import gsw.fingerprint as fp

    seen, real = {}, fp.fingerprint

    def spy(*args, **kwargs):
        seen["config"] = kwargs["config"]
        return real(*args, **kwargs)

    monkeypatch.setattr(fp, "fingerprint", spy)
    assert _fingerprint(model_dir, tmp_path, "recipient\nalice\n", "--novel-views", "0.5", "--view-bank", "3") == 0
    assert seen["config"].novel_views == 0.5 and seen["config"].view_bank == 3
    assert (tmp_path / "out" / "alice" / "point_cloud" / "iteration_0" / "point_cloud.ply").is_file()


def test_the_measured_setting_reaches_the_pool(model_dir, tmp_path, capsys, monkeypatch) -> None:
    """`--early-stop assured --mse 35 --no-fgd` (the best measured setting before the pool's default took the squared
    error without FGD) runs a job whose pool gets that term, no FGD, and the rule that redraws hard messages."""
    import gsw.fingerprint as fp
    from gsw.fingerprint.stopping import EarlyStop

    seen, real = {}, fp.fingerprint

    def spy(*args, **kwargs):
        seen.update(config=kwargs["config"], early_stop=kwargs["early_stop"])
        return real(*args, **kwargs)

    monkeypatch.setattr(fp, "fingerprint", spy)
    assert _fingerprint(model_dir, tmp_path, "recipient\nalice\n", "--early-stop", "assured", "--mse", "35",
                        "--no-fgd") == 0
    cfg = seen["config"]
    assert (cfg.weights.l1, cfg.weights.mse, cfg.fgd) == (0.0, 35.0, False)
    assert seen["early_stop"] == EarlyStop.parse("focused,redraw=2")
    assert (tmp_path / "out" / "alice" / "point_cloud" / "iteration_0" / "point_cloud.ply").is_file()


def test_the_default_recipe_and_stop_rule(model_dir, tmp_path, capsys, monkeypatch) -> None:
    """With no flags the pool gets its default recipe (pool_config()) and the `quality` stop rule; `--early-stop none`
    runs every recipient for --epochs passes; `--mse 0 --fgd --freeze none --mask exp` is the paper's recipe."""
    import gsw.fingerprint as fp
    from gsw.fingerprint.batched import pool_config
    from gsw.fingerprint.stopping import EarlyStop
    from gsw.mark.embed import PAPER_RECIPE

    seen, real = [], fp.fingerprint

    def spy(*args, **kwargs):
        seen.append((kwargs["config"], kwargs["early_stop"]))
        return real(*args, **kwargs)

    monkeypatch.setattr(fp, "fingerprint", spy)
    assert _fingerprint(model_dir, tmp_path, "recipient\nalice\n") == 0
    bare = build_parser().parse_args(["fingerprint", "m", "--recipients", "r.csv", "--output", "o", "--early-stop"])
    assert bare.early_stop == "quality"
    cfg, rule = seen[-1]
    assert rule == EarlyStop.parse("quality")
    assert (cfg.weights.l1, cfg.weights.mse, cfg.weights.message) == (pool_config().weights.l1, 35.0, 0.15)
    assert (cfg.fgd, cfg.freeze, cfg.mask) == (False, ("f_rest",), "none")  # --lpips none: its weight 0
    (tmp_path / "b").mkdir()
    assert _fingerprint(model_dir, tmp_path / "b", "recipient\nbob\n", "--early-stop", "none", "--mse", "0", "--fgd",
                        "--freeze", "none", "--mask", "exp") == 0
    cfg, rule = seen[-1]
    assert rule is None and "2 steps" in capsys.readouterr().out  # 1 epoch of 2 views
    assert (cfg.weights.l1, cfg.weights.mse, cfg.fgd, cfg.freeze, cfg.mask) == (
        1.0, 0.0, True, PAPER_RECIPE["freeze"], PAPER_RECIPE["mask"])


def test_novel_views_outside_0_1_are_refused(model_dir, tmp_path, capsys) -> None:
    assert _fingerprint(model_dir, tmp_path, "recipient\nalice\n", "--novel-views", "1.5") == 2
    err = capsys.readouterr().err
    assert "EmbedConfig.novel_views is a probability in [0, 1], got 1.5" in err
    assert not (tmp_path / "out").exists() and not (tmp_path / "marks.sqlite").exists()  # nothing written


def test_a_negative_view_bank_is_refused(model_dir, tmp_path, capsys) -> None:
    assert _fingerprint(model_dir, tmp_path, "recipient\nalice\n", "--novel-views", "0.5", "--view-bank", "-1") == 2
    assert "EmbedConfig.view_bank must be an integer >= 0, got -1" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_malformed_recipients_file(model_dir, tmp_path, capsys) -> None:
    assert _fingerprint(model_dir, tmp_path, "recipient,message\nalice,\nbob,00,extra\n") == 2
    err = capsys.readouterr().err
    assert "recipients.csv:3" in err and "3 fields" in err
    assert not (tmp_path / "out").exists()
    assert _fingerprint(model_dir, tmp_path, "recipient\nbob\nBOB\n") == 2
    assert "duplicate recipient name" in capsys.readouterr().err
    assert _fingerprint(model_dir, tmp_path, "recipient,message\nbob,xyz\n") == 2  # checked before any write
    assert "message of 'bob'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists() and not (tmp_path / "marks.sqlite").exists()


def test_missing_inputs_are_named(model_dir, tmp_path, capsys) -> None:
    args = ["--output", str(tmp_path / "out"), "--registry", str(tmp_path / "marks.sqlite"), "--local"]
    assert main(["fingerprint", str(model_dir), "--recipients", str(tmp_path / "none.csv"), *args]) == 2
    assert f"recipients file {tmp_path / 'none.csv'}: no such file" in capsys.readouterr().err
    assert main(["fingerprint", str(model_dir), "--recipients", str(tmp_path), *args]) == 2
    assert "a folder, not a file" in capsys.readouterr().err
    (tmp_path / "r.csv").write_text("recipient\nbob\n")
    assert main(["fingerprint", str(tmp_path / "nomodel"), "--recipients", str(tmp_path / "r.csv"), *args]) == 2
    assert f"{tmp_path / 'nomodel'}: no such model file" in capsys.readouterr().err
    assert not (tmp_path / "out").exists() and not (tmp_path / "marks.sqlite").exists()


@pytest.fixture(scope="module")
def crawl(tmp_path_factory):
    """A folder of one image marked for 'alice', one unmarked image and a text file; the registry."""
    from gsw.mark.image import ImageEmbedConfig, embed_image
    from gsw.render.rasterize import rasterize

    root = tmp_path_factory.mktemp("crawl")
    scene = default_scene(width=128, height=128, n_cameras=2, detail=0.5)
    photo = rasterize(scene.gaussians, scene.cameras[0], background=scene.background).image.clamp(0, 1)
    marked = embed_image(photo, "c0ffee42", config=ImageEmbedConfig(seed=0), progress=False)
    (root / "web" / "sub").mkdir(parents=True)
    write_image(root / "web" / "sub" / "leak.png", marked.image)
    write_image(root / "web" / "plain.png", torch.rand(3, 96, 96))
    (root / "web" / "notes.txt").write_text("not an image")
    with open_registry(root / "marks.sqlite") as reg:
        sha = shipped_decoder_sha256(32)
        reg.add_many([dict(label="alice", message="c0ffee42", decoder_sha256=sha),
                      dict(label="bob", message="12345678", decoder_sha256=sha)])
    return root


def test_scan_reports_detections(crawl, capsys) -> None:
    report = crawl / "report.csv"
    assert main(["scan", str(crawl / "web"), "--registry", str(crawl / "marks.sqlite"), "--output", str(report),
                 "--local", "--device", "cpu"]) == 0
    rows = {r["source"].rsplit("/", 1)[-1]: r for r in csv.DictReader(report.open(encoding="utf-8"))}
    assert set(rows) == {"leak.png", "plain.png"}
    assert rows["leak.png"]["identified"] == "alice" and float(rows["leak.png"]["best_adjusted_p"]) <= 1e-6
    assert rows["plain.png"]["identified"] == ""
    assert "c0ffee42" not in report.read_text()
    err = capsys.readouterr().err
    assert "1 identified" in err and "scan [" in err and "2/2" in err  # the progress bar over the sources
    js = crawl / "report.json"
    assert main(["scan", str(crawl / "web" / "*.png"), "--registry", str(crawl / "marks.sqlite"), "--output",
                 str(js), "--local", "--no-progress"]) == 1  # only the unmarked image matches: nobody identified
    assert "scan [" not in capsys.readouterr().err
    data = json.loads(js.read_text())
    assert [r["identified"] for r in data] == [""] and data[0]["images"] == 1


def test_scan_bad_input(crawl, capsys) -> None:
    reg = str(crawl / "marks.sqlite")
    assert main(["scan", str(crawl / "missing"), "--registry", reg, "--local"]) == 2
    assert "no such file or folder" in capsys.readouterr().err
    assert main(["scan", str(crawl / "web"), "--registry", reg, "--output", str(crawl / "r.txt"), "--local"]) == 2
    assert ".csv or .json" in capsys.readouterr().err
    assert main(["scan", str(crawl / "web"), "--registry", str(crawl / "none.sqlite"), "--local"]) == 2
