"""Tests for gsw.data.images.read_image: every PNG/JPEG pixel format at its full range, clear errors."""

from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from gsw.camera import MAX_IMAGE_SIZE
from gsw.data.images import ImageError, read_image, read_rgb, write_image

_EIGHT = 1 / 255 + 1e-6


def png_bytes(arr: np.ndarray, bit_depth: int, color_type: int, *, palette: np.ndarray | None = None,
              trns: bytes | None = None, size: tuple[int, int] | None = None) -> bytes:
    """A PNG written by hand (Pillow cannot write 16-bit colour or 1/2/4-bit grayscale).

    ``arr`` is ``[H, W]`` or ``[H, W, C]`` of sample values; colour types: 0 gray, 2 RGB, 3 palette,
    4 gray+alpha, 6 RGBA. ``size`` overrides the (width, height) in the header.
    """
    h, w = arr.shape[:2]

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    if bit_depth == 16:
        rows = arr.astype(">u2").reshape(h, -1).view(np.uint8).reshape(h, -1)
    elif bit_depth == 8:
        rows = arr.astype(np.uint8).reshape(h, -1)
    else:  # pack 1/2/4-bit samples, most significant first
        per = 8 // bit_depth
        a = np.pad(arr.reshape(h, w).astype(np.uint8), ((0, 0), (0, (-w) % per))).reshape(h, -1, per)
        rows = np.zeros(a.shape[:2], np.uint8)
        for i in range(per):
            rows |= a[:, :, i] << (8 - bit_depth * (i + 1))
    width, height = size or (w, h)
    out = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, bit_depth, color_type, 0, 0, 0))
    if palette is not None:
        out += chunk(b"PLTE", np.asarray(palette, np.uint8).tobytes())
    if trns is not None:
        out += chunk(b"tRNS", trns)
    data = b"".join(b"\0" + row.tobytes() for row in rows)
    return out + chunk(b"IDAT", zlib.compress(data)) + chunk(b"IEND", b"")


def _read(tmp_path: Path, data: bytes, name: str = "x.png") -> torch.Tensor:
    (tmp_path / name).write_bytes(data)
    return read_image(tmp_path / name)


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t.permute(1, 2, 0).numpy()


RNG = np.random.default_rng(0)


def test_16_bit_grayscale_is_not_white(tmp_path):
    """Pillow opens it as mode "I;16"; converting that to RGB clips at 255 (the image read as pure white)."""
    a = RNG.integers(0, 65536, (5, 7))
    img = _read(tmp_path, png_bytes(a, 16, 0))
    assert img.shape == (3, 5, 7) and img.dtype == torch.float32
    for c in range(3):
        np.testing.assert_allclose(img[c].numpy(), a / 65535, rtol=0, atol=1e-6)
    with_alpha = _read(tmp_path, png_bytes(a, 16, 0, trns=struct.pack(">H", int(a[1, 2]))))
    assert with_alpha.shape == (4, 5, 7) and float(with_alpha[3, 1, 2]) == 0.0 and float(with_alpha[3].sum()) >= 34


@pytest.mark.parametrize("color_type, channels", [(2, 3), (6, 4), (4, 2)])
def test_16_bit_colour_and_alpha(tmp_path, color_type, channels):
    a = RNG.integers(0, 65536, (6, 5, channels))
    img = _hwc(_read(tmp_path, png_bytes(a, 16, color_type)))
    expected = a / 65535
    if channels == 2:  # gray + alpha -> RGBA
        expected = np.concatenate([expected[..., :1].repeat(3, -1), expected[..., 1:]], -1)
    assert img.shape == expected.shape
    np.testing.assert_allclose(img, expected, rtol=0, atol=_EIGHT)  # Pillow keeps the top 8 bits


@pytest.mark.parametrize("bit_depth", [1, 2, 4, 8])
def test_low_bit_depth_grayscale(tmp_path, bit_depth):
    top = 2**bit_depth - 1
    a = RNG.integers(0, top + 1, (4, 9))
    img = _read(tmp_path, png_bytes(a, bit_depth, 0))
    assert img.shape == (3, 4, 9)
    np.testing.assert_allclose(img[1].numpy(), a / top, rtol=0, atol=1e-6)


def test_palette_with_and_without_transparency(tmp_path):
    palette = RNG.integers(0, 256, (16, 3))
    a = RNG.integers(0, 16, (5, 6))
    img = _hwc(_read(tmp_path, png_bytes(a, 4, 3, palette=palette)))
    np.testing.assert_allclose(img, palette[a] / 255, rtol=0, atol=1e-6)
    alpha = np.full(16, 255, np.uint8)
    alpha[3] = 0
    img = _hwc(_read(tmp_path, png_bytes(a, 4, 3, palette=palette, trns=alpha.tobytes())))
    assert img.shape == (5, 6, 4)
    np.testing.assert_array_equal(img[..., 3], (a != 3).astype(np.float32))


def test_8_bit_modes_via_pillow(tmp_path):
    from PIL import Image

    rgba = RNG.integers(0, 256, (6, 5, 4)).astype(np.uint8)
    cases = {"RGBA": rgba, "RGB": rgba[..., :3], "L": rgba[..., 0], "LA": rgba[..., :2]}
    for mode, arr in cases.items():
        buf = io.BytesIO()
        Image.fromarray(arr, mode).save(buf, format="PNG")
        img = _hwc(_read(tmp_path, buf.getvalue()))
        expected = arr.astype(np.float64) / 255
        if mode in ("L", "LA"):
            gray = expected if mode == "L" else expected[..., 0]
            expected = np.stack([gray] * 3, -1) if mode == "L" else np.concatenate(
                [np.stack([gray] * 3, -1), expected[..., 1:]], -1)
        np.testing.assert_allclose(img, expected, rtol=0, atol=1e-6, err_msg=mode)


def _smooth_rgb(h: int = 32, w: int = 40) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([x / w, y / h, 0.5 + 0.3 * np.sin(x / 6)], -1)


def test_jpeg_rgb_grayscale_and_cmyk(tmp_path):
    from PIL import Image

    rgb = _smooth_rgb()
    im = Image.fromarray((rgb * 255).round().astype(np.uint8), "RGB")
    for mode in ("RGB", "L", "CMYK"):
        buf = io.BytesIO()
        im.convert(mode).save(buf, format="JPEG", quality=95)
        img = _hwc(_read(tmp_path, buf.getvalue(), f"{mode}.jpg"))
        assert img.shape == (32, 40, 3), mode
        expected = rgb if mode != "L" else np.asarray(im.convert("L"), np.float64)[..., None].repeat(3, -1) / 255
        assert np.abs(img - expected).mean() < 0.02, mode  # JPEG loss only: not inverted, not channel-swapped


def test_unsupported_modes_are_named(tmp_path):
    from PIL import Image

    for mode, arr in (("F", np.zeros((3, 4), np.float32)), ("I", np.zeros((3, 4), np.int32))):
        Image.fromarray(arr, mode).save(tmp_path / f"{mode}.tiff")
        with pytest.raises(ImageError, match=rf"{mode}.tiff: unsupported pixel format \(Pillow mode '{mode}'\)"):
            read_image(tmp_path / f"{mode}.tiff")


def test_bad_files(tmp_path):
    with pytest.raises(ImageError, match="cannot decode image .*x.png"):
        _read(tmp_path, b"definitely not an image")
    good = png_bytes(RNG.integers(0, 256, (20, 20, 3)), 8, 2)
    with pytest.raises(ImageError, match="cannot decode image .*x.png"):
        _read(tmp_path, good[: len(good) // 2])
    with pytest.raises(ImageError, match="cannot decode image"):
        _read(tmp_path, b"", "empty.png")
    (tmp_path / "dir.png").mkdir()
    with pytest.raises(ImageError, match="dir.png: is a directory"):
        read_image(tmp_path / "dir.png")
    with pytest.raises(FileNotFoundError, match="image not found"):
        read_image(tmp_path / "absent.png")
    assert issubclass(ImageError, ValueError)


def test_size_limit_is_checked_before_decoding(tmp_path):
    """The header claims 20000 x 1 pixels; the check fires before Pillow allocates anything."""
    data = png_bytes(np.zeros((1, 1), np.uint8), 8, 0, size=(20000, 1))
    with pytest.raises(ImageError, match=rf"x.png: image is 20000x1; sides must be in 1..{MAX_IMAGE_SIZE} pixels"):
        _read(tmp_path, data)


@pytest.mark.parametrize("bit_depth", [1, 2, 4, 8])
def test_grayscale_colour_key_at_every_bit_depth(tmp_path, bit_depth):
    """Pillow keeps a 2/4-bit tRNS key raw while it rescales the pixels; the key must hit the right pixels."""
    top = 2**bit_depth - 1
    a = np.array([[0, 1, top, 1, 0]])
    img = _read(tmp_path, png_bytes(a, bit_depth, 0, trns=struct.pack(">H", 1)))
    assert img.shape == (4, 1, 5)
    np.testing.assert_array_equal(img[3, 0].numpy(), (a[0] != 1).astype(np.float32))


def test_16_bit_rgb_colour_key_is_rejected_by_name(tmp_path):
    a = np.array([[[0, 0, 0], [256, 256, 256]]])
    with pytest.raises(ImageError, match="16-bit RGB PNG with a tRNS colour key is not supported"):
        _read(tmp_path, png_bytes(a, 16, 2, trns=struct.pack(">HHH", 256, 256, 256)))
    assert _read(tmp_path, png_bytes(a, 16, 2)).shape == (3, 1, 2)  # without the key: fine


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_to_unit_is_the_float_reader_bitwise(device):
    from gsw.data.images import to_unit

    every = torch.arange(256, dtype=torch.uint8, device=device)
    expected = np.arange(256, dtype=np.uint8).astype(np.float32) / np.float32(255.0)  # read_image's division
    out = to_unit(every)
    assert out.dtype == torch.float32 and out.device.type == device
    assert torch.equal(out.cpu(), torch.from_numpy(expected))
    floats = torch.tensor([-0.5, 0.25, 1.5], device=device, dtype=torch.float64)
    assert torch.equal(to_unit(floats).cpu(), torch.tensor([0.0, 0.25, 1.0]))


def test_keep_uint8_keeps_8_bit_colour_only(tmp_path):
    from PIL import Image

    from gsw.data.images import to_unit

    rgba = RNG.integers(0, 256, (6, 5, 4)).astype(np.uint8)
    for mode, arr, kept in (("RGB", rgba[..., :3], True), ("L", rgba[..., 0], True), ("RGBA", rgba, False),
                            ("LA", rgba[..., :2], False)):
        path = tmp_path / f"{mode}.png"
        Image.fromarray(arr, mode).save(path)
        as_float, raw = read_image(path), read_image(path, keep_uint8=True)
        assert raw.dtype == (torch.uint8 if kept else torch.float32), mode
        assert torch.equal(to_unit(raw) if kept else raw, as_float), mode
    path = tmp_path / "photo.jpg"
    Image.fromarray(rgba[..., :3], "RGB").save(path, quality=90)
    assert torch.equal(to_unit(read_image(path, keep_uint8=True)), read_image(path))
    sixteen = tmp_path / "16.png"
    Image.fromarray((RNG.integers(0, 65536, (6, 5))).astype(np.uint16)).save(sixteen)
    assert read_image(sixteen, keep_uint8=True).dtype == torch.float32  # 16-bit: never cut to 8 bits


def test_read_rgb_composites_alpha_on_black(tmp_path):
    rgba = torch.rand(4, 6, 5)
    write_image(tmp_path / "a.png", rgba)
    write_image(tmp_path / "b.png", rgba[:3])
    stored = read_image(tmp_path / "a.png")
    assert stored.shape[0] == 4
    assert torch.equal(read_rgb(tmp_path / "a.png"), stored[:3] * stored[3:])
    assert torch.equal(read_rgb(tmp_path / "b.png"), read_image(tmp_path / "b.png"))
    assert read_rgb(tmp_path / "b.png", keep_uint8=True).dtype == torch.uint8
    with pytest.raises(FileNotFoundError):
        read_rgb(tmp_path / "missing.png")
