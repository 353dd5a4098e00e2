"""gsw.mark.scales and gsw.mark.evidence: reading at the embedding scale, the scale search, assess()."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from gsw.decoder.null import NullModel, NullModelError
from gsw.mark.evidence import CONFIDENT_SHARE, assess, reading_weights
from gsw.mark.scales import MAX_READ_SIDE, MIN_READ_SIDE, SEARCH_FACTORS, read_images, read_plan
from gsw.stats import binomial_p_value, hommel_combined_p_value


class ScaleToy(torch.nn.Module):
    """A decoder that reads ``message`` only from images of height ``target`` and its complement from any
    other height (a watermark that only the right scale reveals); ``confident``: the logits at ``target`` are
    twice as large (the decoder's confidence peaks at the embedding scale), else all readings are equally
    confident."""

    def __init__(self, message: torch.Tensor, target: int, confident: bool = False) -> None:
        super().__init__()
        self.num_bits = message.numel()
        self.register_buffer("message", message.float())
        self.target = target
        self.confident = confident
        self.seen: list[tuple[int, ...]] = []

    def decode_image(self, images: torch.Tensor) -> torch.Tensor:
        self.seen.append(tuple(images.shape))
        hit = images.shape[-2] == self.target
        code = self.message if hit else 1 - self.message
        return ((2 * code - 1) * (2.0 if hit and self.confident else 1.0)).expand(images.shape[0], -1)

    def parameters(self, recurse: bool = True):  # read_images asks for the device
        yield self.message


MSG = torch.tensor([1, 0, 0, 1] * 8)


def test_read_plan_limits_and_embed_size():
    assert [f for f, _ in read_plan(100, 100)] == [1.0, 2 / 3, 2.0]  # 1/2 and 1/3 fall below MIN_READ_SIDE
    big = read_plan(900, 600)
    assert all(max(s) <= MAX_READ_SIDE and min(s) >= MIN_READ_SIDE for _, s in big) and 2.0 not in [f for f, _ in big]
    assert read_plan(20, 20) == [(1.0, (20, 20))]  # the first factor is always read
    assert read_plan(512, 512, embed_size=(256, 256)) == [(0.5, (256, 256))]
    (f, size), = read_plan(300, 600, embed_size=(256, 256))  # other aspect ratio: same pixel count
    assert size == (181, 362) and f == pytest.approx(256 / (300 * 600) ** 0.5)
    with pytest.raises(ValueError, match="height, width"):
        read_plan(10, 10, embed_size=(0, 5))


def test_read_images_batches_same_sizes():
    dec = ScaleToy(MSG, 128)
    imgs = [torch.rand(3, 256, 256) for _ in range(3)] + [torch.rand(3, 128, 192)]
    readings = read_images(imgs, dec)
    assert [len(r.factors) for r in readings] == [5, 5, 5, 4]
    assert len(dec.seen) == 9 and dec.seen[0][0] == 3  # one decode per reading of each shape group
    assert readings[0].sizes[2] == (128, 128) and torch.equal(readings[0].bits[2], MSG.float())
    with pytest.raises(ValueError, match="image 1"):
        read_images([torch.rand(3, 8, 8), torch.rand(8, 8)], dec)


@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def test_uint8_images_read_as_their_float_images_bitwise(device):
    """The scan's readers keep 8-bit images as uint8; mixed with float images of the same shape, the shipped
    decoder's logits equal those of the float32 images (divided by 255 on the decoder's device)."""
    from gsw.data.images import to_unit
    from gsw.decoder.zoo import load_decoder

    raw = [torch.randint(0, 256, (3, 96, 128), dtype=torch.uint8, generator=torch.Generator().manual_seed(i))
           for i in range(3)]
    dec = load_decoder(32).to(device).eval()
    mixed = read_images([raw[0], to_unit(raw[1]), raw[2]], dec)
    floats = read_images([to_unit(r) for r in raw], dec)
    for a, b in zip(mixed, floats):
        assert a.sizes == b.sizes and torch.equal(a.logits, b.logits)


def test_scale_search_picks_the_embedding_scale_and_pays_for_the_search():
    img = torch.rand(3, 256, 256)  # a render at 2x the embedding resolution
    s = len(SEARCH_FACTORS)
    for confident, weight in ((True, CONFIDENT_SHARE + (1 - CONFIDENT_SHARE) / s), (False, (1 - CONFIDENT_SHARE) / s)):
        # the decoder's confidence points at the right reading (weight 0.6 of 5 readings) or at another one
        dec, null = ScaleToy(MSG, 128, confident), NullModel.fair(32)
        ev = assess([img], MSG, num_bits=32, decoder=dec, null=null, origin="chosen")
        (e,) = ev.images
        assert e.factor == 0.5 and e.read_size == (128, 128) and e.matches == 32 and e.readings == s
        assert e.p_value == pytest.approx(2.0**-32 / weight)
    dec, null = ScaleToy(MSG, 128), NullModel.fair(32)
    known = assess([img], MSG, num_bits=32, decoder=dec, null=null, embed_size=(128, 128), origin="chosen")
    assert known.images[0].readings == 1 and known.p_value == pytest.approx(2.0**-32)
    wrong = assess([img], MSG, num_bits=32, decoder=dec, null=null, embed_size=(256, 256), origin="chosen")
    assert wrong.images[0].matches == 0 and wrong.p_value == 1.0 and not wrong.detected()


def test_identical_frames_are_not_counted_as_independent_evidence():
    dec, null = ScaleToy(MSG, 64), NullModel.fair(32)
    msg = MSG.clone()
    msg[:3] = 1 - msg[:3]  # 29 of 32 bits at the right scale
    frames = [torch.full((3, 64, 64), 0.5)] * 10
    ev = assess(frames, msg, num_bits=32, decoder=dec, null=null, embed_size=(64, 64), origin="chosen")
    harmonic = sum(1 / i for i in range(1, 11))
    assert ev.matches == [29] * 10
    assert ev.p_value == pytest.approx(harmonic * binomial_p_value(29, 32))
    assert not ev.detected(1e-6)


def test_assess_errors():
    dec = ScaleToy(MSG, 64)
    with pytest.raises(ValueError, match=r"expected \[32\] bits"):
        assess([torch.rand(3, 64, 64)], MSG[:31], num_bits=32, decoder=dec, null=NullModel.fair(32))
    with pytest.raises(ValueError, match="0 or 1"):
        assess([torch.rand(3, 64, 64)], MSG * 2, num_bits=32, decoder=dec, null=NullModel.fair(32))
    with pytest.raises(NullModelError, match="48 bits given for num_bits=32"):
        assess([torch.rand(3, 64, 64)], MSG, num_bits=32, decoder=dec, null=NullModel.fair(48))
    other = NullModel.fair(32)
    other.decoder_fingerprint = "0" * 64
    with pytest.raises(NullModelError, match="not for this decoder"):
        assess([torch.rand(3, 64, 64)], MSG, num_bits=32, decoder=dec, null=other)
    ev = assess([torch.rand(3, 64, 64)], MSG, num_bits=32, decoder=dec, origin="chosen")  # custom, no null model
    assert ev.null_model == "fair" and ev.origin == "chosen"
    with pytest.raises(ValueError, match="origin must be one of random, chosen"):
        assess([torch.rand(3, 64, 64)], MSG, num_bits=32, decoder=dec, origin="picked")
    with pytest.raises(ValueError, match="weighting must be one of"):
        assess([torch.rand(3, 64, 64)], MSG, num_bits=32, decoder=dec, weighting="fancy")


def test_shipped_decoder_on_noise_is_not_detected():
    imgs = [torch.rand(3, 96, 96), torch.rand(3, 96, 96)]
    ev = assess(imgs, np.ones(32, dtype=int), num_bits=32, origin="chosen")
    assert ev.null_model == "calibrated" and len(ev.images) == 2 and not ev.detected()
    ev = assess(imgs, np.ones(32, dtype=int), num_bits=32)
    assert ev.null_model == "exact" and ev.origin == "random" and len(ev.images) == 2 and not ev.detected()


def test_extract_reads_at_the_embedding_size_when_known(tmp_path, capsys):
    from gsw.cli.main import main
    from gsw.data.images import resize_image, write_image
    from gsw.mark import extract

    g = torch.Generator().manual_seed(5)
    big = torch.rand(3, 128, 96, generator=g)  # e.g. a render at 2x the 64x48 embedding size
    small = resize_image(big[None], 64, 48)[0]
    known = extract(big, num_bits=32, embed_size=(64, 48))
    assert torch.equal(known.logits, extract(small, num_bits=32).logits)  # the same reading as verify's
    assert not torch.equal(extract(big, num_bits=32).logits, known.logits)  # without it: the image as given
    write_image(tmp_path / "big.png", big)
    assert main(["extract", str(tmp_path / "big.png"), "--embed-size", "48x64", "--json"]) == 0
    from gsw.data.images import read_image

    expected = extract(read_image(tmp_path / "big.png"), num_bits=32, embed_size=(64, 48)).hex[0]
    assert json.loads(capsys.readouterr().out)[0]["hex"] == expected
    with pytest.raises(SystemExit) as exc:
        main(["extract", str(tmp_path / "big.png"), "--embed-size", "48"])
    assert exc.value.code == 2 and "WIDTHxHEIGHT" in capsys.readouterr().err


def test_score_messages_of_a_chosen_message_is_the_null_model_p_value():
    from gsw.decoder.null import load_null_model
    from gsw.mark.evidence import score_messages
    from gsw.mark.scales import Reading

    gen = np.random.default_rng(0)
    null = load_null_model(32)
    readings = [Reading([1.0, 0.5, 2.0], [(64, 64), (32, 32), (128, 128)], torch.randn(3, 32)) for _ in range(4)]
    msgs = gen.integers(0, 2, (6, 32)).astype(np.int8)
    sc = score_messages(readings, msgs, null, origin="chosen")
    for j, m in enumerate(msgs):
        per = [null.p_values(r.bits.numpy().astype(np.int8), m, np.asarray(r.factors)) / reading_weights(r.confidence)
               for r in readings]
        assert sc.p_values[:, j] == pytest.approx([min(1.0, p.min()) for p in per])
        assert sc.chosen[:, j].tolist() == [int(np.argmin(p)) for p in per]
        assert sc.combined[j] == pytest.approx(float(hommel_combined_p_value(sc.p_values[:, j])))


def test_a_set_of_frames_read_enlarged_is_detected_with_the_scale_search():
    """Issue #22 anomaly (lego, renders at 0.5x: 400 px of an 800-px embedding): every frame read all 32
    bits at factor 2 and passed 1e-6 alone, yet no set of 10 did, because the search paid the 5 readings
    per frame before Hommel's factor (2.9 for 10) on the null model's p-value of 32 matches read enlarged.
    The decoder's confidence points at that reading; it gets most of the level."""
    from gsw.decoder.null import load_null_model
    from gsw.mark.evidence import score_messages
    from gsw.mark.message import random_message
    from gsw.mark.scales import Reading
    from gsw.stats import DETECTION_FPR

    null = load_null_model(32)
    msg = random_message(32, seed=2222).numpy().astype(np.int8)  # the lego run's message
    plan = read_plan(400, 400)
    assert [f for f, _ in plan] == list(SEARCH_FACTORS) and plan[-1][1] == (800, 800)
    gen = torch.Generator().manual_seed(0)
    readings = []
    for _ in range(10):
        logits = 0.3 * torch.randn(len(plan), 32, generator=gen)  # the other scales read noise
        logits[-1] = 3.0 * (2 * torch.from_numpy(msg).float() - 1)  # factor 2: the message, confidently
        readings.append(Reading([f for f, _ in plan], [s for _, s in plan], logits))
    sc = score_messages(readings, msg[None], null, origin="chosen")
    weight = CONFIDENT_SHARE + (1 - CONFIDENT_SHARE) / len(plan)
    perfect = null.tail_table(msg, "up")[32]
    harmonic = sum(1 / i for i in range(1, 11))
    assert sc.chosen[:, 0].tolist() == [len(plan) - 1] * 10 and sc.matches[:, 0].tolist() == [32] * 10
    assert sc.p_values[:, 0] == pytest.approx([perfect / weight] * 10)
    assert sc.combined[0] == pytest.approx(harmonic * perfect / weight)
    assert sc.combined[0] <= DETECTION_FPR and all(p <= DETECTION_FPR for p in sc.p_values[:, 0])


def test_reading_weights():
    w = reading_weights(torch.tensor([0.2, 0.9, 0.9, 0.1]))  # the first of the most confident gets the share
    assert w.sum() == pytest.approx(1.0) and w.argmax() == 1
    assert w[1] == pytest.approx(CONFIDENT_SHARE + (1 - CONFIDENT_SHARE) / 4) and w[2] == pytest.approx(w[0])
    assert reading_weights(np.array([3.0])).tolist() == [1.0]  # one reading (known size): no factor
    for bad in (np.zeros(0), np.zeros((2, 2))):
        with pytest.raises(ValueError, match="shape"):
            reading_weights(bad)
