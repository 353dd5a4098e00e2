"""Run folders of the pre-training (gsw.decoder.pretrain.runs)."""

import json

import pytest
import torch

from gsw.decoder.hidden import HiddenDecoder
from gsw.decoder.pretrain.config import MultiConfig
from gsw.decoder.pretrain.encoders import make_encoder
from gsw.decoder.pretrain.runs import config_dict, load_init, load_run_decoder, read_meta, write_stage
from gsw.decoder.whitening import WhiteningLayer


def _write_run(out, cfg, half=False, ft=True):
    torch.manual_seed(0)
    enc, dec = make_encoder(8, cfg), HiddenDecoder(8, cfg.dec_blocks, cfg.channels, cfg.dec_norm)
    wl = WhiteningLayer(8)
    with torch.no_grad():
        wl.weight.mul_(2.0)
    meta = {"num_bits": 8, "config": config_dict(cfg, 8, 0.0), "steps": 3, "results": {}}
    write_stage(out, "done", 8, meta, dec, wl, 3, {"encoder": enc, **({"encoder_ft": enc} if ft else {})}, half)
    return enc, dec, wl


def test_write_stage_then_load_back(tmp_path):
    cfg = MultiConfig(bits=(8,), channels=8, enc_blocks=1, dec_blocks=2)
    enc, dec, wl = _write_run(tmp_path, cfg)
    meta = read_meta(tmp_path, 8)
    assert meta["stage"] == "done" and meta["config"]["num_bits"] == 8 and meta["config"]["channels"] == 8
    d2, w2, _ = load_run_decoder(tmp_path, 8)
    assert not d2.training and torch.equal(w2.weight, wl.weight)
    ll = torch.rand(2, 3, 8, 8)
    with torch.no_grad():
        assert torch.equal(d2(ll), dec.eval()(ll))
    encs, decs = load_init(tmp_path, cfg, "encoder_ft")
    x, m = torch.rand(1, 3, 16, 16), torch.randint(0, 2, (1, 8)).float()
    with torch.no_grad():
        assert torch.equal(encs[0].eval()(x, m), enc.eval()(x, m))


def test_run_errors_name_the_file(tmp_path):
    cfg = MultiConfig(bits=(8,), channels=8, enc_blocks=1, dec_blocks=2)
    with pytest.raises(FileNotFoundError, match="k8.json"):
        read_meta(tmp_path, 8)
    _write_run(tmp_path, cfg, ft=False)
    with pytest.raises(ValueError, match="has no 'encoder_ft'"):
        load_init(tmp_path, cfg, "encoder_ft")
    wider = MultiConfig(bits=(8,), channels=16, enc_blocks=1, dec_blocks=2)
    with pytest.raises(ValueError, match="do not fit this configuration"):
        load_init(tmp_path, wider)
    (tmp_path / "k8.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        read_meta(tmp_path, 8)


def test_half_runs_store_float16_encoders(tmp_path):
    cfg = MultiConfig(bits=(8,), channels=8, enc_blocks=1, dec_blocks=2)
    _write_run(tmp_path, cfg, half=True)
    blob = torch.load(tmp_path / "k8.pt", weights_only=False)
    assert blob["encoder"]["final.weight"].dtype == torch.float16
    assert blob["decoder"]["linear.weight"].dtype == torch.float32
    assert json.loads((tmp_path / "k8.json").read_text())["steps"] == 3
