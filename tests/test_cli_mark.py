"""`gsw embed` / `extract` / `verify` / `embed-image` options: model folders, watermark.json, devices, outputs."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import shutil
from pathlib import Path

import pytest
import torch

from gsw.camera import save_inria_cameras
from gsw.cli.main import build_parser, main
from gsw.cli.mark import embed_config
from gsw.data import load_inria_model, save_inria_model, write_image
from gsw.decoder.zoo import load_decoder
from gsw.eval.grid import decoder_fingerprint
from gsw.mark import verify
from gsw.mark.message import message_from_key, message_to_hex
from gsw.scenes import default_scene

KEY = "studio-secret-7"


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _run(argv: list[str]) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(argv)
    return rc, out.getvalue()


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    scene = default_scene(width=48, height=48, n_cameras=4, detail=0.4)
    folder = tmp_path_factory.mktemp("model")
    save_inria_model(folder, scene.gaussians, scene.cameras, iteration=100)
    return folder


@pytest.fixture(scope="module")
def marked(model_dir, tmp_path_factory) -> tuple[Path, dict, dict]:
    """A 48-bit, white-background model embedded from a key on the CPU: (folder, stdout summary, input digest)."""
    before = _digest(model_dir)
    out = tmp_path_factory.mktemp("marked") / "m"
    rc, text = _run(["embed", str(model_dir), "--output", str(out), "--key", KEY, "--bits", "48", "--white",
                     "--epochs", "1", "--lpips", "none", "--device", "cpu", "--no-progress", "--json",
                     "--fpr", "1"])  # one epoch is not detectable at 1e-6: test_cli_embed_check.py tests that
    assert rc == 0
    return out, json.loads(text), before


def test_embed_writes_a_new_folder_and_never_touches_the_input(model_dir, marked, tmp_path) -> None:
    out, summary, before = marked
    assert summary["message"] == message_to_hex(message_from_key(KEY, 48)) and len(summary["bits"]) == 48
    assert (out / "point_cloud" / "iteration_0" / "point_cloud.ply").is_file()
    assert (out / "cameras.json").is_file() and (out / "watermark.json").is_file()
    assert _digest(model_dir) == before
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temporary left
    # refuses to overwrite an existing output, or to write into the input
    args = ["--epochs", "1", "--lpips", "none", "--no-progress"]
    assert main(["embed", str(model_dir), "--output", str(out), *args]) == 2
    assert main(["embed", str(model_dir), "--output", str(model_dir / "sub"), *args]) == 2
    assert _digest(model_dir) == before


def test_watermark_json_records_what_verify_needs(marked) -> None:
    out, summary, _ = marked
    record = json.loads((out / "watermark.json").read_text())
    assert (record["num_bits"], record["background"], record["resolution"]) == (48, [1.0] * 3,
                                                                                  {"width": 48, "height": 48})
    assert record["decoder"]["fingerprint"] == decoder_fingerprint(load_decoder(48))
    assert record["gsw_version"] and record["embedding"]["epochs"] == 1
    assert {k: summary[k] for k in record} == record  # --json prints the record plus the message


def _bit_lists(obj: object, n: int) -> list:
    if isinstance(obj, dict):
        return [x for v in obj.values() for x in _bit_lists(v, n)]
    if isinstance(obj, list):
        own = [obj] if len(obj) == n and all(v in (0, 1) for v in obj) else []
        return own + [x for v in obj for x in _bit_lists(v, n)]
    return []


def test_no_output_file_holds_the_message_or_the_key(marked) -> None:
    out, summary, _ = marked
    message = summary["message"]
    files = [p for p in out.rglob("*") if p.is_file()]
    assert len(files) >= 3
    for path in files:
        data = path.read_bytes().lower()
        for secret in (KEY.lower(), message, "".join(map(str, summary["bits"]))):
            assert secret.encode() not in data, (path, secret)
    assert _bit_lists(json.loads((out / "watermark.json").read_text()), 48) == []


def _verify_json(argv: list[str]) -> dict:
    rc, text = _run(["verify", *argv, "--fpr", "1.0", "--device", "cpu", "--json"])
    assert rc == 0
    return json.loads(text)


def test_verify_model_uses_the_stored_bits_background_and_resolution(marked, tmp_path, capsys) -> None:
    out, _, _ = marked
    model = load_inria_model(out)
    message = message_from_key(KEY, 48)
    white = verify((model.gaussians, model.cameras), message, background=(1.0, 1.0, 1.0),
                   embed_size=(model.cameras[0].height, model.cameras[0].width))
    black = verify((model.gaussians, model.cameras), message, background=(0.0, 0.0, 0.0),
                   embed_size=(model.cameras[0].height, model.cameras[0].width))
    assert white.p_values != black.p_values  # the background changes what the decoder reads
    check = marked[1]["verification"]  # embed's own check: the same calibrated test (4 views: none held out)
    assert check["held_out"] is False and check["p_value"] == pytest.approx(white.p_value)
    report = _verify_json(["--model", str(out), "--key", KEY])  # no --bits, no --white
    assert (report["num_bits"], report["background"]) == (48, [1.0, 1.0, 1.0])
    assert [v["p_value"] for v in report["views"]] == pytest.approx(white.p_values)
    report = _verify_json(["--model", str(out), "--key", KEY, "--black"])
    assert [v["p_value"] for v in report["views"]] == pytest.approx(black.p_values)
    # cameras.json at twice the size: rendered at the embedding resolution all the same
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    save_inria_cameras([c.scaled(2.0) for c in model.cameras], copy / "cameras.json")
    report = _verify_json(["--model", str(copy), "--key", KEY])
    assert [v["p_value"] for v in report["views"]] == pytest.approx(white.p_values)
    # a hex message of another length than the model's is refused, naming the file
    assert main(["verify", "--model", str(out), "--message", "0123abcd"]) == 2
    assert "watermark.json" in capsys.readouterr().err
    (copy / "watermark.json").write_text("{")
    assert main(["verify", "--model", str(copy), "--key", KEY]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gsw verify: error: ") and str(copy / "watermark.json") in err


def test_verify_model_takes_the_message_origin_from_watermark_json(marked, tmp_path) -> None:
    out, _, _ = marked
    assert json.loads((out / "watermark.json").read_text())["message_origin"] == "random"  # a key: message
    assert _verify_json(["--model", str(out), "--key", KEY])["origin"] == "random"
    chosen = tmp_path / "chosen"
    shutil.copytree(out, chosen)
    record = json.loads((chosen / "watermark.json").read_text())
    record["message_origin"] = "chosen"
    (chosen / "watermark.json").write_text(json.dumps(record))
    report = _verify_json(["--model", str(chosen), "--key", KEY])  # no --chosen-message needed
    assert report["origin"] == "chosen"


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
    assert main(["extract", str(out), "--json"]) == 0  # the folder: the same images, sorted
    assert json.loads(capsys.readouterr().out) == rows
    assert main(["verify", *pngs, "--message", rows[0]["hex"], "--fpr", "1e-6"]) in (0, 1)
    # 16 hex digits without --bits: a 64-bit message
    assert _verify_json([*pngs[:1], "--message", "0123456789abcdef"])["num_bits"] == 64


def test_verify_chosen_message_flag_selects_the_calibrated_test(tmp_path, capsys) -> None:
    img = tmp_path / "a.png"
    write_image(img, torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(3)))
    from gsw.data.images import read_image

    image = read_image(img)
    for flag, origin in (([], "random"), (["--chosen-message"], "chosen")):
        report = _verify_json([str(img), "--message", "0123abcd", *flag])
        expected = verify([image], "0123abcd", origin=origin)
        assert report["origin"] == origin and report["p_value"] == pytest.approx(expected.p_value)
    assert (verify([image], "0123abcd", origin="chosen").p_value
            != pytest.approx(verify([image], "0123abcd").p_value))  # two different tests
    assert main(["verify", str(img), "--message", "0123abcd", "--device", "cpu"]) == 1
    assert "random message: exact test" in capsys.readouterr().out
    assert main(["verify", str(img), "--message", "0123abcd", "--device", "cpu", "--chosen-message"]) == 1
    assert "chosen message: calibrated null model" in capsys.readouterr().out
    with pytest.raises(ValueError, match="origin must be one of random, chosen"):
        verify([image], "0123abcd", origin="typed")


@pytest.mark.parametrize("argv, match", [
    (["verify", "x.png", "--message", "0123abcd", "--key", "k"], "not both"),
    (["verify", "x.png", "--key", ""], "--key is empty"),
    (["verify", "x.png", "--message", "0123abcd01"], "--bits"),
    (["verify", "x.png"], "--message HEX or --key SECRET"),
    (["embed-image", "x.png", "--output", "y.png", "--message", "0123abcd", "--key", "k"], "not both"),
    (["embed", "in", "--output", "out", "--key", ""], "--key is empty"),
])
def test_bad_message_options_are_errors(argv, match, capsys) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert match in err and err.count("\n") == 1


def test_bad_cli_inputs(tmp_path, capsys) -> None:
    assert main(["embed", str(tmp_path / "missing"), "--output", str(tmp_path / "o")]) == 2
    assert main(["extract", str(tmp_path / "nope.png")]) == 2
    assert "error" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["embed", "x", "--output", "y", "--bits", "31"])
    img = tmp_path / "a.png"
    write_image(img, torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(0)))
    for argv in (["verify", str(img), "--key", "k"], ["embed-image", str(img), "--output", str(tmp_path / "b.png")]):
        assert main([*argv, "--device", "tpu"]) == 2  # one device rule everywhere
        assert "device must be 'auto', 'cpu', 'cuda' or 'cuda:N'" in capsys.readouterr().err
    assert main(["verify", str(img), "--key", "k", "--device", "cpu"]) == 1


def test_embed_robustness_flags_reach_the_config() -> None:
    from gsw.mark.loss import LossWeights

    args = build_parser().parse_args(["embed", "in", "--output", "out", "--attacks", "0.5",
                                      "--model-attack-prob", "0.5", "--message-weight", "0.1"])
    cfg = embed_config(args)
    assert (cfg.attacks, cfg.model_attacks, cfg.weights.message) == (0.5, 0.5, 0.1)
    assert cfg.background == (0.0, 0.0, 0.0)
    default = embed_config(build_parser().parse_args(["embed", "in", "--output", "out", "--white"]))
    assert default.model_attacks == 0.0 and default.weights.message == LossWeights().message
    assert default.background == (1.0, 1.0, 1.0)


def test_fgd_is_the_recipes_unless_asked() -> None:
    def cfg(*extra: str):
        return embed_config(build_parser().parse_args(["embed", "in", "--output", "out", *extra]))

    assert not cfg().fgd and cfg("--recipe", "paper").fgd  # the library default has none; the paper's recipe has it
    assert cfg("--fgd").fgd and not cfg("--recipe", "paper", "--no-fgd").fgd


def test_mse_sets_the_image_term_in_embed_and_fingerprint(capsys) -> None:
    """The default recipe's image term is the squared error (35), the paper's and the pool's L1; ``--mse W`` sets
    it, ``--mse 0`` picks L1."""
    from gsw.fingerprint.batched import pool_config
    from gsw.mark.loss import LossWeights

    def weights(*argv: str, base=None):
        return embed_config(build_parser().parse_args(list(argv)), base).weights

    default = weights("embed", "in", "--output", "out")
    assert (default.l1, default.mse) == (0.0, 35.0) == (LossWeights().l1, LossWeights().mse)
    paper = weights("embed", "in", "--output", "out", "--recipe", "paper")
    assert (paper.l1, paper.mse) == (1.0, 0.0)
    w = weights("embed", "in", "--output", "out", "--mse", "20", "--message-weight", "0.2")
    assert (w.l1, w.mse, w.message) == (0.0, 20.0, 0.2)
    l1 = weights("embed", "in", "--output", "out", "--mse", "0")
    assert (l1.l1, l1.mse, l1.message) == (1.0, 0.0, LossWeights().message)
    fp = ["fingerprint", "in", "--recipients", "r.csv", "--output", "out"]
    pool, pool_l1 = weights(*fp, base=pool_config()), weights(*fp, "--mse", "0", base=pool_config())
    assert (pool.l1, pool.mse, pool_l1.l1, pool_l1.mse) == (0.0, 35.0, 1.0, 0.0)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["embed", "in", "--output", "out", "--mse", "-1"])
    assert "must be a number >= 0" in capsys.readouterr().err


def test_embed_render_scales_reach_the_config_and_are_checked(capsys) -> None:
    args = build_parser().parse_args(["embed", "in", "--output", "out", "--render-scales", "0.5", "1"])
    assert embed_config(args).render_scales == (0.5, 1.0)
    default = embed_config(build_parser().parse_args(["embed", "in", "--output", "out"]))
    assert default.render_scales == (1.0, 1.0)
    with pytest.raises(ValueError, match="LOW <= HIGH"):
        embed_config(build_parser().parse_args(["embed", "in", "--output", "out", "--render-scales", "1", "0.5"]))
    with pytest.raises(SystemExit):
        build_parser().parse_args(["embed", "in", "--output", "out", "--render-scales", "0", "1"])
    assert "must be a positive number" in capsys.readouterr().err


def test_embed_a_bare_ply_without_cameras_samples_views(model_dir, tmp_path, monkeypatch) -> None:
    import dataclasses

    import gsw.cli.mark as cli_mark

    def small(args):  # the CLI's config, with few small sampled views (a CPU test)
        return dataclasses.replace(embed_config(args), sampled_views=2, sampled_view_size=64)

    monkeypatch.setattr(cli_mark, "embed_config", small)
    ply = model_dir / "point_cloud" / "iteration_100" / "point_cloud.ply"
    out = tmp_path / "bare"
    rc, text = _run(["embed", str(ply), "--output", str(out), "--epochs", "1", "--lpips", "none", "--no-fgd",
                     "--device", "cpu", "--no-progress", "--fpr", "1", "--json"])
    assert rc == 0  # --fpr 1: one epoch is not detectable at 1e-6; the check runs on the sampled views
    assert "embedding view" in json.loads(text)["verification"]["where"]
    model = load_inria_model(out)
    assert len(model.cameras) == 2 and all((c.width, c.height) == (64, 64) for c in model.cameras)
    assert json.loads(text)["output"] == str(out)


# ------------------------------------------------------------------------------------------------ --readout


def _klein(num_bits: int):
    from gsw.decoder import KleinReadout

    return KleinReadout(load_decoder(num_bits))


def test_embed_readout_klein_records_the_wrapper_and_verify_reads_through_it(model_dir, marked, tmp_path,
                                                                             capsys) -> None:
    from gsw.decoder.readout import shipped_klein_fingerprint
    from gsw.registry import open_registry

    out, reg = tmp_path / "k", tmp_path / "marks.sqlite"
    rc, text = _run(["embed", str(model_dir), "--output", str(out), "--key", KEY, "--bits", "48", "--white",
                     "--epochs", "1", "--lpips", "none", "--device", "cpu", "--no-progress", "--fpr", "1",
                     "--readout", "klein", "--label", "kim", "--registry", str(reg), "--json"])
    assert rc == 0
    summary = json.loads(text)
    record = json.loads((out / "watermark.json").read_text())
    assert record["decoder"]["fingerprint"] == decoder_fingerprint(_klein(48)) != decoder_fingerprint(load_decoder(48))
    with open_registry(reg, create=False) as r:  # what gsw identify / gsw scan recognise the readout by
        assert r.get("kim").decoder_sha256 == shipped_klein_fingerprint(48)
    # verify --model --readout klein is gsw.verify(decoder=KleinReadout(...)) on the stored background and size
    model = load_inria_model(out)
    size = (model.cameras[0].height, model.cameras[0].width)
    klein = verify((model.gaussians, model.cameras), message_from_key(KEY, 48), background=(1.0, 1.0, 1.0),
                   embed_size=size, decoder=_klein(48))
    direct = verify((model.gaussians, model.cameras), message_from_key(KEY, 48), background=(1.0, 1.0, 1.0),
                    embed_size=size)
    assert klein.p_values != pytest.approx(direct.p_values)  # the readout changes what is read
    report = _verify_json(["--model", str(out), "--key", KEY, "--readout", "klein"])
    assert [v["p_value"] for v in report["views"]] == pytest.approx(klein.p_values)
    assert summary["verification"]["p_value"] == pytest.approx(klein.p_value)  # embed's own check reads it so too
    # the other readout is refused, naming the flag to use (watermark.json's fingerprint says which it was)
    capsys.readouterr()
    assert main(["verify", "--model", str(out), "--key", KEY, "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert "watermarked through the klein readout" in err and "pass --readout klein" in err
    assert main(["verify", "--model", str(marked[0]), "--key", KEY, "--readout", "klein", "--device", "cpu"]) == 2
    assert "pass --readout direct" in capsys.readouterr().err
    # a watermark.json written before 2026-11-28 (the legacy short fingerprint) still names its readout
    from gsw.eval.grid.store import legacy_decoder_fingerprint

    record["decoder"]["fingerprint"] = legacy_decoder_fingerprint(_klein(48))
    (out / "watermark.json").write_text(json.dumps(record))
    assert main(["verify", "--model", str(out), "--key", KEY, "--device", "cpu"]) == 2
    assert "pass --readout klein" in capsys.readouterr().err


def test_embed_image_extract_and_verify_with_readout_klein_match_the_python_api(tmp_path, capsys) -> None:
    import gsw
    from gsw.data.images import read_image

    src, out = tmp_path / "src.png", tmp_path / "out.png"
    write_image(src, 0.25 + 0.5 * torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(0)))
    assert main(["embed-image", str(src), "--output", str(out), "--key", KEY, "--steps", "20", "--psnr", "32",
                 "--readout", "klein", "--device", "cpu", "--no-progress", "--json"]) == 0
    capsys.readouterr()
    image = read_image(out)
    assert main(["extract", str(out), "--readout", "klein", "--json"]) == 0
    bits = json.loads(capsys.readouterr().out)[0]["bits"]
    expected = gsw.extract(image, num_bits=32, decoder=_klein(32)).bits[0]
    assert bits == expected.int().tolist() == message_from_key(KEY, 32).int().tolist()  # every bit, not chance
    report = _verify_json([str(out), "--key", KEY, "--readout", "klein"])
    assert report["p_value"] == pytest.approx(gsw.verify([image], f"key:{KEY}", num_bits=32,
                                                         decoder=_klein(32)).p_value)
    assert main(["verify", str(out), "--key", KEY, "--readout", "klein", "--device", "cpu"]) == 0  # at 1e-6
    assert "random message: exact test" in capsys.readouterr().out
    # A chosen message through the klein readout is tested against the null model calibrated through it
    # (gsw/decoder/weights/null_k32_klein.json), as the Python API does.
    hex_message = message_to_hex(message_from_key(KEY, 32))
    report = _verify_json([str(out), "--message", hex_message, "--chosen-message", "--readout", "klein"])
    expected = gsw.verify([image], hex_message, decoder=_klein(32), origin="chosen")
    assert report["test"] == expected.test == "calibrated" and report["p_value"] == pytest.approx(expected.p_value)
    assert _verify_json([str(out), "--message", hex_message, "--chosen-message"])["test"] == "calibrated"
    # Where no such model ships (48 bits), a chosen message has no valid test through the readout (the fair coin is
    # anti-conservative for messages aligned with the decoder's lean): refused when verifying and when embedding;
    # the Python API falls back to the fair coin and says so.
    hex48 = message_to_hex(message_from_key(KEY, 48))
    assert main(["verify", str(out), "--message", hex48, "--chosen-message", "--readout", "klein"]) == 2
    assert "no valid test through --readout klein at 48 bits" in capsys.readouterr().err
    assert main(["embed-image", str(src), "--output", str(tmp_path / "o2.png"), "--message", hex48,
                 "--readout", "klein"]) == 2
    assert "use --key SECRET or no message" in capsys.readouterr().err and not (tmp_path / "o2.png").exists()
    assert gsw.verify([image], hex48, decoder=_klein(48), origin="chosen").test == "fair"
    # 64 bits has one (null_k64_klein.json): accepted, and the calibrated test runs.
    hex64 = message_to_hex(message_from_key(KEY, 64))
    report = _verify_json([str(out), "--message", hex64, "--chosen-message", "--readout", "klein", "--bits", "64"])
    assert report["test"] == "calibrated"


@pytest.mark.parametrize("command", [["embed", "in", "--output", "out"], ["embed-image", "x.png", "--output", "y.png"],
                                     ["extract", "x.png"], ["verify", "x.png", "--key", "k"]])
def test_readout_is_direct_by_default_and_an_unknown_one_is_refused(command, capsys) -> None:
    assert build_parser().parse_args(command).readout == "direct"
    assert build_parser().parse_args([*command, "--readout", "klein"]).readout == "klein"
    with pytest.raises(SystemExit) as exc:
        main([*command, "--readout", "fancy"])
    assert exc.value.code == 2 and "invalid choice: 'fancy'" in capsys.readouterr().err
