"""Identification of recipients: p-value per mark, Holm over marks, truly marked images, 1,000 marks."""

from __future__ import annotations

import random

import numpy as np
import pytest
import torch

import gsw.mark
import gsw.mark.identify
from gsw.mark.identify import _holm, decode_sources, identify, identify_readings, plan_identify
from gsw.mark.image import ImageEmbedConfig, embed_image
from gsw.mark.message import random_message
from gsw.registry import Mark, open_registry, shipped_decoder_sha256
from gsw.stats import binomial_p_value

BITS = 48


def test_holm_adjustment() -> None:
    assert _holm([0.01, 0.04, 0.03, 0.5]) == pytest.approx([0.04, 0.09, 0.09, 0.5])
    assert _holm([0.3, 0.3]) == pytest.approx([0.6, 0.6])
    assert _holm([]).size == 0


def test_holm_is_the_step_down_loop_bitwise() -> None:
    """The vectorised adjustment equals the textbook loop (ties ranked in input order) exactly."""
    rng = np.random.default_rng(3)
    for m in (1, 7, 500):
        p = np.round(rng.random(m) ** 3, 3)  # rounded: many ties
        expected, running = [1.0] * m, 0.0
        for rank, i in enumerate(sorted(range(m), key=lambda j: p[j])):
            running = max(running, min(1.0, (m - rank) * float(p[i])))
            expected[i] = running
        assert _holm(p).tolist() == expected


class _CoinDecoder(torch.nn.Module):
    """A decoder that reads fair coins whatever the image: the null hypothesis made exact."""

    def __init__(self, k: int, seed: int) -> None:
        super().__init__()
        self.k, self.gen = k, torch.Generator().manual_seed(seed)

    def forward(self, ll: torch.Tensor) -> torch.Tensor:
        return torch.randn(ll.shape[0], self.k, generator=self.gen)


@pytest.mark.parametrize("origin", ["chosen", "random"])
def test_family_wise_false_positive_rate_holds_under_the_null(origin) -> None:
    """Unmarked sources (coin-flip bits) against 50 marks: P(anyone identified) stays <= fpr."""
    k, fpr, trials, sha = 16, 0.05, 300, "ee" * 32
    messages = random.Random(0).sample(range(2**k), 50)
    marks = [Mark(id=i + 1, label=f"m{i}", message_hex=f"{m:04x}", num_bits=k, decoder_sha256=sha, model_hash=None,
                  width=None, height=None, background=None, created="t", gsw_version="v", origin=origin)
             for i, m in enumerate(messages)]
    decoders = {sha: _CoinDecoder(k, seed=1)}
    image = torch.zeros(3, 32, 32)
    runs = [identify(image, marks, fpr=fpr, decoders=decoders) for _ in range(trials)]
    hits = sum(bool(r.identified) for r in runs)
    assert hits / trials <= fpr + 3 * (fpr * (1 - fpr) / trials) ** 0.5
    # without the correction over marks the same sources would name someone most of the time
    uncorrected = sum(any(m.p_value <= fpr for m in r.results) for r in runs)
    assert uncorrected / trials > 0.5


@pytest.fixture(scope="module")
def marked(tmp_path_factory):
    """A registry of 5 recipients (48 bits, shipped decoder) and a 64x64 image truly marked for 'carol'."""
    path = tmp_path_factory.mktemp("reg") / "reg.sqlite"
    sha = shipped_decoder_sha256(BITS)
    with open_registry(path) as reg:
        for i, name in enumerate(["alice", "bob", "carol", "dave", "erin"]):
            reg.add(name, random_message(BITS, seed=100 + i), decoder_sha256=sha, width=64, height=64)
        carol = reg.get("carol")
    g = torch.Generator().manual_seed(0)
    cover = 0.25 + 0.5 * torch.rand(3, 64, 64, generator=g)
    res = embed_image(cover, carol.message, num_bits=BITS, progress=False,
                      config=ImageEmbedConfig(steps=40, attack_every=0, psnr=32.0, device="cpu"))
    assert res.bit_accuracy == 1.0, "the fixture's image is not fully marked"
    return path, cover, res.image


def test_marked_image_names_its_recipient_and_no_one_else(marked) -> None:
    path, _, image = marked
    with open_registry(path, create=False) as reg:
        found = identify(image, reg)
    assert found.recipients == ["carol"]
    assert len(found.results) == 5 and found.num_images == 1 and not found.skipped
    best = found.identified[0]
    assert best.matches == [BITS] and best.adjusted_p_value <= found.fpr and best.exact
    # the calibrated evidence of gsw.verify at the registered embedding size, Holm over 5 marks
    claim = gsw.mark.verify([image], best.mark.message, num_bits=BITS, embed_size=(64, 64), origin="chosen")
    assert best.p_value == pytest.approx(claim.p_value) and best.p_value >= binomial_p_value(BITS, BITS)
    assert best.adjusted_p_value == pytest.approx(5 * claim.p_value)
    assert all(not r.identified and r.adjusted_p_value > found.fpr for r in found.results[1:])
    assert "message_hex" not in str(found.to_dict()) and found.to_dict()["recipients"] == ["carol"]


def test_unmarked_image_names_nobody(marked) -> None:
    path, cover, _ = marked
    with open_registry(path, create=False) as reg:
        found = identify([cover, cover.flip(-1)], reg)
    assert found.identified == [] and found.recipients == []
    assert len(found.results) == 5 and all(r.adjusted_p_value > found.fpr for r in found.results)


def test_marked_video_frames_name_the_recipient(marked, tmp_path) -> None:
    av = pytest.importorskip("av")
    from gsw.io.video import load_images_or_video

    path, cover, image = marked
    video = tmp_path / "leak.mkv"
    frames = [cover, image, image, cover]  # the marked copy appears in the middle of the clip
    with av.open(str(video), "w") as container:
        stream = container.add_stream("ffv1", rate=4)
        stream.width, stream.height, stream.pix_fmt = 64, 64, "bgr0"  # lossless
        for f in frames:
            arr = np.ascontiguousarray((f * 255).round().to(torch.uint8).permute(1, 2, 0).numpy())
            container.mux(stream.encode(av.VideoFrame.from_ndarray(arr, format="rgb24")))
        container.mux(stream.encode())
    with open_registry(path, create=False) as reg:
        found = identify(load_images_or_video([video], frames=None), reg)
    assert found.recipients == ["carol"] and found.num_images == 4
    assert found.identified[0].matches[1:3] == [BITS, BITS]


def test_a_thousand_marks_decode_once_and_stay_correct(marked, tmp_path, monkeypatch) -> None:
    _, cover, image = marked
    sha = shipped_decoder_sha256(BITS)
    path = tmp_path / "big.sqlite"
    with open_registry(path) as reg:
        with open_registry(marked[0], create=False) as small:
            carol = small.get("carol")
        reg.add_many([dict(label=f"recipient-{i}", message=random_message(BITS, seed=10_000 + i),
                           decoder_sha256=sha) for i in range(999)])
        reg.add("carol", carol.message, decoder_sha256=sha)
        assert len(reg) == 1000
        calls = []
        real_read = gsw.mark.identify.read_images

        def counting_read(images, decoder, **kwargs):
            calls.append((decoder.num_bits, kwargs.get("embed_size")))
            return real_read(images, decoder, **kwargs)

        monkeypatch.setattr(gsw.mark.identify, "read_images", counting_read)
        found = identify([image, cover], reg)
        nobody = identify([cover], reg)
    assert calls == [(BITS, None)] * 2  # one decoding pass of the images per call, not one per mark
    assert found.recipients == ["carol"] and len(found.results) == 1000
    claim = gsw.mark.verify([image, cover], carol.message, num_bits=BITS, origin="chosen")  # no size: scale search
    assert found.identified[0].adjusted_p_value == pytest.approx(1000 * claim.p_value)
    assert sum(r.exact for r in found.results) >= 10
    assert nobody.recipients == []


def test_keep_reports_the_best_marks_and_every_identified_one(marked) -> None:
    """``keep`` trims the report, not the test: Holm still counts every mark, and no identified mark is dropped."""
    path, cover, image = marked
    with open_registry(path, create=False) as reg:
        plan = plan_identify(reg.list(), device="cpu")
    marked_src, cover_src = decode_sources([[image], [cover]], plan)
    full = identify_readings(marked_src, plan)
    for keep in (0, 1, 3):
        kept = identify_readings(marked_src, plan, keep=keep)
        assert kept.recipients == full.recipients == ["carol"]  # the identified mark survives keep=0
        assert [r.to_dict(True) for r in kept.results] == [r.to_dict(True) for r in full.results[:max(keep, 1)]]
    nobody = identify_readings(cover_src, plan, keep=1)
    assert nobody.identified == [] and len(nobody.results) == 1
    assert nobody.results[0].to_dict(True) == identify_readings(cover_src, plan).results[0].to_dict(True)
    assert identify_readings(cover_src, plan, keep=0).results == []
    with pytest.raises(ValueError, match="keep"):
        identify_readings(cover_src, plan, keep=-1)


def test_screening_keeps_the_decisions_and_bounds_the_screened_p_values(marked) -> None:
    path, cover, image = marked
    with open_registry(path, create=False) as reg:
        marks = reg.list()
    for source in ([image, cover], [cover]):
        full = identify(source, marks, exact=len(marks))
        screened = identify(source, marks, exact=0)
        assert all(r.exact for r in full.results)
        assert screened.recipients == full.recipients
        exact = {r.mark.id: r.p_value for r in full.results}
        assert any(not r.exact for r in screened.results)
        for r in screened.results:
            if r.exact:  # could be identified: computed exactly
                assert r.p_value == pytest.approx(exact[r.mark.id]) and r.p_value <= full.fpr
            else:  # a lower bound of the calibrated value, already above the fpr
                assert full.fpr < r.p_value <= exact[r.mark.id] + 1e-15


def test_marks_of_unknown_decoders_are_skipped_and_custom_decoders_used(marked) -> None:
    path, _, image = marked
    with open_registry(path, create=False) as reg:
        marks = reg.list()
    from dataclasses import replace

    foreign = replace(marks[0], id=99, label="foreign", decoder_sha256="12" * 32)
    found = identify(image, [*marks, foreign])
    assert [m.label for m in found.skipped] == ["foreign"] and len(found.results) == 5
    assert found.recipients == ["carol"]
    # the same decoder given under the foreign sha256: now the foreign mark is tested too
    from gsw.decoder import load_decoder

    found = identify(image, [*marks, foreign], decoders={"12" * 32: load_decoder(BITS)})
    assert not found.skipped and len(found.results) == 6


def test_marks_embedded_through_the_klein_readout_are_recognised(tmp_path) -> None:
    from gsw.decoder import KleinReadout, load_decoder
    from gsw.decoder.readout import shipped_klein_fingerprint

    klein = KleinReadout(load_decoder(BITS))
    path = tmp_path / "reg.sqlite"
    with open_registry(path) as reg:
        reg.add("kim", random_message(BITS, seed=7), decoder_sha256=shipped_klein_fingerprint(BITS), width=64,
                height=64, origin="random")
        reg.add("dan", random_message(BITS, seed=8), decoder_sha256=shipped_decoder_sha256(BITS), width=64, height=64,
                origin="random")
        kim = reg.get("kim")
    cover = 0.25 + 0.5 * torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(1))
    res = embed_image(cover, kim.message, num_bits=BITS, decoder=klein, progress=False,
                      config=ImageEmbedConfig(steps=40, attack_every=0, psnr=32.0, device="cpu"))
    assert res.bit_accuracy == 1.0
    with open_registry(path, create=False) as reg:
        found = identify(res.image, reg)  # no decoders given: the readout is recognised from the registry record
        plain = identify(cover, reg)
    assert found.recipients == ["kim"] and not found.skipped and len(found.results) == 2
    assert plain.recipients == [] and not plain.skipped


def test_bad_arguments(marked) -> None:
    path, _, image = marked
    with open_registry(path, create=False) as reg:
        with pytest.raises(ValueError, match="fpr must lie in"):
            identify(image, reg, fpr=0.0)
        with pytest.raises(ValueError, match="no images"):
            identify([], reg)
        with pytest.raises(ValueError, match="expected a \\[3,H,W\\]"):
            identify([torch.rand(1, 64, 64)], reg)


def test_each_mark_is_tested_by_its_message_origin(marked) -> None:
    """Random marks get the exact test of gsw.verify (no screening), chosen marks the calibrated one; Holm over all."""
    from dataclasses import replace

    path, cover, image = marked
    with open_registry(path, create=False) as reg:
        marks = reg.list()
    mixed = [replace(m, origin="random" if i % 2 else "chosen") for i, m in enumerate(marks)]  # carol: chosen
    for source in ([image], [image, cover]):
        found = identify(source, mixed, exact=0)
        assert found.recipients == ["carol"]
        for r in found.results:
            if r.exact:
                claim = gsw.mark.verify(source, r.mark.message, num_bits=BITS, embed_size=(64, 64),
                                        origin=r.mark.origin)
                assert r.p_value == pytest.approx(claim.p_value)
            assert r.exact or r.mark.origin == "chosen"  # only chosen marks are screened
            assert r.to_dict()["origin"] == r.mark.origin
    carol = next(m for m in marks if m.label == "carol")
    found = identify([image], [replace(carol, origin="random")])
    claim = gsw.mark.verify([image], carol.message, num_bits=BITS, embed_size=(64, 64))  # origin random
    assert found.recipients == ["carol"] and found.results[0].p_value == pytest.approx(claim.p_value)
    assert claim.p_value == pytest.approx(2.0**-BITS)  # every bit read: the exact test's smallest p-value
