"""Export of decoders and the report's measurements (gsw.decoder.pretrain.export)."""

import json
from pathlib import Path

import pytest
import torch

from gsw.decoder import load_decoder
from gsw.decoder.pretrain.export import export_shipped, jpeg_fidelity, measure_unbiased, merge_ft_runs, write_report
from gsw.decoder.pretrain.report import markdown

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Small inputs: torch's intra-op threads only add overhead (and contention on a shared machine)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_jpeg_fidelity_orders_the_codecs_and_adapts_the_crop_to_small_photos():
    g = torch.Generator().manual_seed(0)
    smooth = torch.nn.functional.interpolate(torch.rand(2, 3, 12, 16, generator=g), size=(96, 128), mode="bilinear")
    jf = jpeg_fidelity(list((smooth * 255).round().to(torch.uint8)), qualities=(90, 30))
    assert jf["num_images"] == 2 and jf["side"] == 96
    q90, q30 = jf["psnr_db"]["90"], jf["psnr_db"]["30"]
    assert q90["real_vs_orig"] > q30["real_vs_orig"]  # stronger compression, lower PSNR
    assert q90["diff_vs_real"] > 25


def test_measure_unbiased_sections():
    g = torch.Generator().manual_seed(0)
    photos = [(torch.rand(3, 40, 56, generator=g) * 255).to(torch.uint8) for _ in range(3)]
    stats = measure_unbiased(load_decoder(32), photos, num_fit=200)
    w, raw, rc = stats["unbiased_whitened"], stats["unbiased_raw"], stats["cpu_recheck"]
    assert w["num_images"] == raw["num_images"] == rc["num_images"] == 3 and w["num_messages"] == 1000
    assert w["views_num"] == 30 and w["fit_images"] == 200
    assert {n: w[n] for n in rc} == rc  # the re-check is the whitened measurement on the photos alone


def test_export_shipped_needs_the_training_records(tmp_path):
    with pytest.raises(ValueError, match=r"no run record for \[48\] bits"):
        export_shipped({"runs": {"32": {}}}, tmp_path, tmp_path / "w", (32, 48))


def test_merge_ft_runs_and_write_report(tmp_path):
    rep = json.loads((RESULTS / "decoder.json").read_text())
    ft = tmp_path / "ft"
    ft.mkdir()
    r = {**rep["runs"]["32"]["results"]["pair_raw"], "n": 8}
    r["bit_acc"] = {**r["bit_acc"], "identity": 0.99}
    (ft / "k32.json").write_text(json.dumps({"results": {"pair_raw_ft": r, "pair_raw": r}, "device": "X",
                                             "config": {"ft_s": 5.0, "ft_target": "raw"}, "ft_steps": 9}))
    merge_ft_runs(rep, [ft], (32, 48))
    got = rep["runs"]["32"]["results"]["pair_raw_ft"]
    assert got["bit_acc"]["identity"] == 0.99 and got["n"] == 8 and got["ft_steps"] == 9 and got["device"] == "X"
    assert got["config"]["ft_target"] == "raw" and rep["runs"]["32"]["results"]["pair_raw"] != r  # only *_ft
    js, md = write_report({"runs": {"32": rep["runs"]["32"]}, "cpu_recheck": rep["cpu_recheck"],
                           "jpeg_fidelity": rep["jpeg_fidelity"]}, tmp_path / "out" / "dec")
    assert json.loads(js.read_text())["runs"]["32"]["results"]["pair_raw_ft"]["ft_steps"] == 9
    assert md.read_text() == markdown(json.loads(js.read_text()), [32])
