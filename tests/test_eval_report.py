"""The watermark evaluation report and `gsw eval`."""

from __future__ import annotations

import json
import math

import pytest

from gsw.attacks import gaussian_noise, jpeg, remove_random
from gsw.cli.main import main
from gsw.data import save_inria_model
from gsw.mark.detect import verify
from gsw.eval.report import DETECTION_FPR, evaluate_watermark
from gsw.render.rasterize import rasterize
from gsw.scenes import default_scene


@pytest.fixture(scope="module")
def scene():
    return default_scene(width=48, height=48, n_cameras=3, detail=0.4)


def test_report_on_identical_models(scene) -> None:
    g = scene.gaussians
    rep = evaluate_watermark(g, g, scene.cameras, "0x12345678", lpips_net=None,
                             image_attacks={"noise": gaussian_noise, "jpeg": jpeg},
                             model_attacks={"remove": remove_random})
    assert math.isinf(rep.psnr) and rep.ssim == pytest.approx(1.0, abs=1e-4) and rep.lpips is None
    # the same model is both "watermarked" and "original": identical detection
    assert rep.clean == rep.unmarked
    assert set(rep.image_attacks) == {"noise", "jpeg"} and set(rep.model_attacks) == {"remove"}
    for d in list(rep.image_attacks.values()) + list(rep.model_attacks.values()):
        assert 0.0 <= d.bit_accuracy <= 1.0 and 0.0 <= d.detected_views <= 1.0
    md = rep.to_markdown()
    assert "| noise | image |" in md and "| remove | model |" in md


def test_report_sees_a_changed_model(scene) -> None:
    g = scene.gaussians
    changed = g.clone()
    changed.sh[:, 0] += 0.05
    rep = evaluate_watermark(changed, g, scene.cameras, [0, 1] * 16, lpips_net="alex",
                             image_attacks={}, model_attacks={}, official=True)
    assert 20 < rep.psnr < 60 and rep.lpips is not None and rep.lpips > 0
    assert {k for k in rep.image_attacks} == {"official_noise", "official_blur", "official_crop", "official_jpeg"}
    with pytest.raises(ValueError, match="camera"):
        evaluate_watermark(g, g, [], "0x12345678")


def test_report_keeps_p_values_and_can_attack_the_original(scene) -> None:
    g = scene.gaussians
    changed = g.clone()
    changed.sh[:, 0] += 0.05
    rep = evaluate_watermark(changed, g, scene.cameras, "0x12345678", lpips_net=None, image_attacks={"jpeg": jpeg},
                             model_attacks={"remove": remove_random}, attack_unmarked=True)
    for d in (rep.clean, rep.unmarked, rep.image_attacks["jpeg"], rep.unmarked_model_attacks["remove"]):
        assert len(d.p_values) == 3 and all(0.0 < p <= 1.0 for p in d.p_values)
        assert d.detected_views == sum(p <= DETECTION_FPR for p in d.p_values) / 3
    # the unmarked tables are the attacks on the original model's renders / on the original model
    plain = [rasterize(g, c).image.clamp(0, 1) for c in scene.cameras]
    assert rep.unmarked_image_attacks["jpeg"].p_values == verify([jpeg(x) for x in plain], "0x12345678").p_values
    assert rep.unmarked_model_attacks["remove"].p_values == verify((remove_random(g), scene.cameras),
                                                                   "0x12345678").p_values
    assert "| jpeg | image |" in rep.to_markdown() and "original: views at p <= 1e-6 |" in rep.to_markdown()
    assert not evaluate_watermark(changed, g, scene.cameras, "0x12345678", lpips_net=None, image_attacks={},
                                  model_attacks={}).unmarked_image_attacks


def test_cli_eval(scene, tmp_path, capsys) -> None:
    save_inria_model(tmp_path / "orig", scene.gaussians, scene.cameras, iteration=1)
    save_inria_model(tmp_path / "marked", scene.gaussians, scene.cameras, iteration=1)
    out = tmp_path / "report.md"
    assert main(["eval", str(tmp_path / "marked"), "--original", str(tmp_path / "orig"), "--message",
                 "0a0b0c0d", "--views", "2", "--lpips", "none", "--output", str(out), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert set(data["image_attacks"]) >= {"noise", "rotation", "jpeg", "crop"}
    assert set(data["model_attacks"]) >= {"parameter_noise", "remove", "clone", "quantize"}
    assert out.read_text().startswith("| measure | value |")
    assert main(["eval", str(tmp_path / "marked"), "--original", str(tmp_path / "orig")]) == 2


def test_cli_eval_reads_the_models_watermark_json(scene, tmp_path, capsys) -> None:
    from gsw.cli.metadata import watermark_record, write_watermark_json
    from gsw.mark.embed import EmbedConfig
    from gsw.mark.message import message_from_key

    changed = scene.gaussians.clone()
    changed.sh[:, 0] += 0.05
    save_inria_model(tmp_path / "orig", scene.gaussians, scene.cameras, iteration=1)
    save_inria_model(tmp_path / "marked", changed, scene.cameras, iteration=1)
    write_watermark_json(tmp_path / "marked", watermark_record(
        num_bits=48, background=(1.0, 1.0, 1.0), cameras=scene.cameras, decoder="-", config=EmbedConfig(), stats={}))
    args = ["eval", str(tmp_path / "marked"), "--original", str(tmp_path / "orig"), "--key", "k", "--lpips", "none",
            "--views", "1", "--device", "cpu", "--json"]
    assert main(args) == 0
    data = json.loads(capsys.readouterr().out)
    message = message_from_key("k", 48)
    for bg, flag in (((1.0, 1.0, 1.0), []), ((0.0, 0.0, 0.0), ["--black"])):
        expected = evaluate_watermark(changed, scene.gaussians, scene.cameras[:1], message, background=bg,
                                      lpips_net=None, image_attacks={}, model_attacks={})
        if flag:
            assert main([*args, *flag]) == 0
            data = json.loads(capsys.readouterr().out)
        assert data["clean"]["p_values"] == pytest.approx(expected.clean.p_values)
        assert data["psnr"] == pytest.approx(expected.psnr)
