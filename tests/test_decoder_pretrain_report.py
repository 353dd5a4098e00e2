"""The decoder report's markdown (gsw.decoder.pretrain.report) regenerates the committed one from its JSON."""

import json
from pathlib import Path

from gsw.decoder.pretrain.report import markdown

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def test_markdown_of_the_committed_report_is_the_committed_markdown():
    rep = json.loads((RESULTS / "decoder.json").read_text())
    bits = sorted(int(b) for b in rep["runs"])
    assert markdown(rep, bits).encode() == (RESULTS / "decoder.md").read_bytes()


def test_markdown_follows_the_numbers_and_the_columns():
    rep = json.loads((RESULTS / "decoder.json").read_text())
    rep["runs"]["48"]["results"]["pair_raw"]["bit_acc"]["identity"] = 0.123
    text = markdown(rep, [48, 64])
    assert "| identity | 12.3 | " in text and "| attack | 48 bits | 64 bits |" in text
    assert "32 bits" not in text
    assert "48 bits: jointly trained encoder: clean 12.30 % (NOT met" in text
