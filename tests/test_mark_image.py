"""gsw.embed_image and `gsw embed-image`: a watermark in a 2-D image, read by gsw.extract / gsw.verify."""

import json

import pytest
import torch
import torch.nn.functional as F

import gsw
from gsw.cli.main import main
from gsw.data.images import read_image, write_image
from gsw.mark.message import message_from_key

FAST = gsw.ImageEmbedConfig(steps=40, attack_every=0, psnr=32.0)


def _photo(h: int = 96, w: int = 80) -> torch.Tensor:
    gen = torch.Generator().manual_seed(3)
    return 0.2 + 0.6 * F.interpolate(torch.rand(1, 3, 9, 9, generator=gen), size=(h, w), mode="bilinear")[0]


def test_embed_image_is_read_back_by_extract_and_leaves_the_input():
    img = _photo()
    copy = img.clone()
    res = gsw.embed_image(img, "key:studio", config=FAST, progress=False)
    assert torch.equal(img, copy)
    assert res.image.shape == img.shape and res.image.dtype == torch.float32
    assert torch.equal((res.image * 255).round() / 255, res.image)  # already 8-bit
    assert torch.equal(res.message, message_from_key("studio", 32)) and len(res.message_hex) == 8
    assert res.bit_accuracy == 1.0 and res.p_value < 1e-6 and abs(res.psnr - 32.0) < 0.3
    assert gsw.extract(res.image).hex[0] == res.message_hex
    assert gsw.verify([res.image], "key:studio", num_bits=32).detected()
    assert not gsw.verify([img], "key:studio", num_bits=32).detected()


def test_embed_image_accepts_uint8_and_other_bit_lengths():
    img = (_photo(64, 64) * 255).round().to(torch.uint8)
    res = gsw.embed_image(img, None, num_bits=48, config=FAST, progress=False)
    assert res.message.shape == (48,) and res.image.shape == (3, 64, 64)
    again = gsw.embed_image(img, None, num_bits=48, config=FAST, progress=False)
    assert not torch.equal(res.message, again.message)  # a fresh secret message each time, not the seed's
    same = gsw.embed_image(img, res.message, num_bits=48, config=FAST, progress=False)
    assert torch.equal(res.image, same.image)  # the seed drives the optimisation: same message, same image


@pytest.mark.parametrize("image, error, match", [
    (torch.rand(4, 64, 64), ValueError, r"\[3,H,W\]"),
    (torch.rand(64, 64), ValueError, r"\[3,H,W\]"),
    (torch.rand(3, 16, 64), ValueError, ">= 32"),
    (torch.full((3, 64, 64), float("nan")), ValueError, "NaN"),
    (torch.rand(3, 64, 64) * 2, ValueError, r"\[0, 1\]"),
    (torch.ones(3, 64, 64, dtype=torch.int32), TypeError, "uint8"),
    ([[0.5]], TypeError, "torch.Tensor"),
])
def test_bad_images_are_named(image, error, match):
    with pytest.raises(error, match=match):
        gsw.embed_image(image, config=FAST, progress=False)


def test_a_custom_decoder_of_another_length_is_named():
    from gsw.decoder.hidden import HiddenDecoder

    with pytest.raises(ValueError, match="expected \\[1, 32\\]"):
        gsw.embed_image(_photo(), decoder=HiddenDecoder(16, num_blocks=1, channels=8), config=FAST, progress=False)
    with pytest.raises(ValueError, match="expected \\[1, 32\\]"):
        gsw.extract(_photo(), decoder=HiddenDecoder(16, num_blocks=1, channels=8))


def test_bad_messages_and_settings_are_named():
    with pytest.raises(ValueError, match="expected 32"):
        gsw.embed_image(_photo(), [1, 0, 1], config=FAST, progress=False)
    for cfg in [gsw.ImageEmbedConfig(steps=-1), gsw.ImageEmbedConfig(psnr=0.0), gsw.ImageEmbedConfig(device="tpu")]:
        with pytest.raises(ValueError):
            gsw.embed_image(_photo(), config=cfg, progress=False)
    if not torch.cuda.is_available():  # gsw.device.resolve_device: an unusable device is a RuntimeError
        with pytest.raises(RuntimeError, match="device 'cuda' requested"):
            gsw.embed_image(_photo(), config=gsw.ImageEmbedConfig(device="cuda"), progress=False)


def test_cli_embed_image_then_verify(tmp_path, capsys):
    src = tmp_path / "photo.png"
    write_image(src, _photo())
    before = src.read_bytes()
    out = tmp_path / "marked.png"
    args = ["embed-image", str(src), "--output", str(out), "--key", "studio", "--steps", "40", "--psnr", "32",
            "--no-progress", "--json"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    assert src.read_bytes() == before and summary["images"][0]["bit_accuracy"] == 1.0
    assert summary["images"][0]["image"] == str(out) and len(summary["bits"]) == 32
    assert main(["verify", str(out), "--key", "studio"]) == 0
    assert main(["verify", str(src), "--key", "studio"]) == 1
    assert main(args) == 2 and "exists" in capsys.readouterr().err  # no silent overwrite
    assert main(["embed-image", str(src), "--output", str(src), "--force"]) == 2  # never the input
    assert main(["embed-image", str(src), "--output", str(tmp_path / "m.jpg")]) == 2
    assert main(["embed-image", str(tmp_path / "missing.png"), "--output", str(tmp_path / "x.png")]) == 2
    assert read_image(out).shape == (3, 96, 80)
    weak = tmp_path / "weak.png"  # no optimisation: noise only, so the exit status says it is not detectable
    assert main(["embed-image", str(src), "--output", str(weak), "--steps", "0", "--no-progress"]) == 1
    assert "not detectable" in capsys.readouterr().err and weak.exists()


def test_embed_images_batches_same_size_images_and_keeps_the_order():
    a, b, c = _photo(96, 80), _photo(64, 64), _photo(96, 80).flip(-1)
    res = gsw.embed_images([a, b, c], "key:studio", config=FAST, batch_size=2, progress=False)
    assert [r.image.shape for r in res] == [a.shape, b.shape, c.shape]
    assert all(r.bit_accuracy == 1.0 and r.message_hex == res[0].message_hex for r in res)
    # one image through embed_images is exactly embed_image
    one = gsw.embed_images([b], "key:studio", config=FAST, progress=False)[0]
    assert torch.equal(one.image, gsw.embed_image(b, "key:studio", config=FAST, progress=False).image)
    with pytest.raises(ValueError, match="image 1: .*>= 32"):
        gsw.embed_images([a, torch.rand(3, 8, 8)], config=FAST, progress=False)
    with pytest.raises(ValueError, match="no images"):
        gsw.embed_images([], config=FAST, progress=False)
    with pytest.raises(ValueError, match="batch_size"):
        gsw.embed_images([a], config=FAST, batch_size=0, progress=False)


def test_cli_embed_image_several_inputs_write_a_new_folder(tmp_path, capsys):
    srcs = []
    for name, img in (("a", _photo()), ("b", _photo(64, 64))):
        srcs.append(tmp_path / "in" / f"{name}.png")
        srcs[-1].parent.mkdir(exist_ok=True)
        write_image(srcs[-1], img)
    out = tmp_path / "in" / "marked"  # a new folder beside the inputs is fine
    args = ["embed-image", *map(str, srcs), "--output", str(out), "--key", "studio", "--steps", "40", "--psnr", "32",
            "--no-progress", "--json"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    assert sorted(p.name for p in out.iterdir()) == ["a.png", "b.png"]
    assert [r["bit_accuracy"] for r in summary["images"]] == [1.0, 1.0]
    assert main(["verify", str(out / "a.png"), str(out / "b.png"), "--key", "studio"]) == 0  # two sizes
    assert main(args) == 2 and "exists" in capsys.readouterr().err
    # never over a folder that holds an input, even with --force; no temporary folders left behind
    assert main([*args[:3], "--output", str(tmp_path / "in"), "--force", "--steps", "1"]) == 2
    assert srcs[0].exists() and not [p for p in (tmp_path / "in").iterdir() if p.name.startswith(".")]
    assert main(["embed-image", str(srcs[0]), str(tmp_path / "a.png"), "--output", str(tmp_path / "o")]) == 2
