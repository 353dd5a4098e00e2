"""The pre-training pipeline (gsw.decoder.pretrain.pipeline): options, and no compiled extension needed."""

import subprocess
import sys

import pytest

from helpers import BLOCK_EXTENSION
import torch

from gsw.decoder.pretrain.pipeline import PretrainOptions, make_val_fn
from gsw.decoder.pretrain.config import MultiConfig
from gsw.decoder.pretrain.encoders import make_encoder
from gsw.decoder.hidden import HiddenDecoder



@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Small inputs: torch's intra-op threads only add overhead (and contention on a shared machine)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_pretraining_and_its_cli_import_without_the_extension():
    mods = ["gsw.decoder.pretrain." + m for m in ("config", "data", "encoders", "loop", "multi", "whiten",
                                                  "evaluation", "runs", "pipeline", "export", "report")]
    code = BLOCK_EXTENSION + "".join(f"import {m}\n" for m in mods + ["gsw.cli.decoder"])
    code += ("import argparse\nfrom gsw.cli.decoder import register\np = argparse.ArgumentParser()\n"
             "register(p.add_subparsers())\np.parse_args(['decoder', 'export', '--help'])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "--shipped" in out.stdout


def test_options_map_to_the_training_config_and_reject_bad_values(tmp_path):
    o = PretrainOptions(data="d", output=str(tmp_path / "run"), bits=(32, 48), steps=7, batch=16, psnr=31.0,
                        time_budget_s=0.0, templates=8)
    cfg = o.multi_config(torch.device("cpu"))
    assert (cfg.bits, cfg.steps, cfg.batch_size, cfg.psnr_target, cfg.templates) == ((32, 48), 7, 16, 31.0, 8)
    assert cfg.time_budget_s is None and not cfg.amp and not cfg.channels_last  # 0 s: the step budget counts
    assert PretrainOptions(data="d", output="o", time_budget_s=5.0).multi_config(torch.device("cpu")).time_budget_s == 5.0
    with pytest.raises(ValueError, match="ft_target must be one of"):
        PretrainOptions(data="d", output="o", ft_target="x").validate()
    with pytest.raises(ValueError, match="cannot be its own init"):
        PretrainOptions(data="d", output=str(tmp_path), init=str(tmp_path)).validate()
    with pytest.raises(ValueError, match="bits must be positive"):
        PretrainOptions(data="d", output="o", bits=()).validate()


def test_validation_reads_every_layer_and_the_view_warp():
    torch.manual_seed(0)
    bank = (torch.rand(3, 3, 40, 48) * 255).to(torch.uint8)
    cfg = MultiConfig(bits=(8,), channels=8, enc_blocks=1, dec_blocks=2, crop=32,
                      noise_layers=("identity", "noise", "jpeg"))
    val_fn = make_val_fn(bank, cfg)
    enc, dec = make_encoder(8, cfg).eval(), HiddenDecoder(8, 2, 8).eval()
    a, b = val_fn([enc], [dec], 30.0), val_fn([enc], [dec], 30.0)
    assert a == b and set(a["k8"]) == {"identity", "noise", "jpeg", "view"}
    assert all(0.0 <= v <= 1.0 for v in a["k8"].values())
