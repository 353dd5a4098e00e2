"""Image file IO (Pillow, atomic writes) and resizing. Tensors are channel-major float32 in ``[0, 1]``.

:func:`read_image` reads every common PNG/JPEG pixel format at its full range: 1/2/4/8-bit and 16-bit
grayscale (``"I;16"``: divided by 65535, not clipped at 255), grayscale + alpha, palette (with or without
``tRNS`` transparency), RGB and RGBA at 8 or 16 bits (Pillow keeps the top 8 bits of 16-bit colour),
CMYK and YCbCr JPEGs. ``tRNS`` colour keys of 2/4-bit grayscale are applied at the right scale (Pillow
compares the raw key with rescaled pixels); 16-bit RGB with a colour key is rejected (Pillow keeps only
8 bits, so the key cannot be matched). Other pixel formats (32-bit integer ``"I"``, float ``"F"``, ``"LAB"``, ...) are
rejected by name, as are images larger than :data:`gsw.camera.MAX_IMAGE_SIZE` on a side (before decoding).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from gsw._atomic import atomic_write
from gsw.camera import MAX_IMAGE_SIZE
from gsw.device import constant

__all__ = ["ImageError", "read_image", "read_rgb", "write_image", "resize_image", "composite", "to_unit",
           "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".PNG", ".JPG", ".JPEG", ".WEBP")

_SIXTEEN_BIT = ("I;16", "I;16B", "I;16L", "I;16N")
_EIGHT_BIT = ("1", "L", "P", "LA", "PA", "La", "RGB", "RGBA", "RGBa", "RGBX", "CMYK", "YCbCr")
_ALPHA_MODES = ("RGBA", "LA", "PA", "La", "RGBa")


class ImageError(ValueError):
    """An image file cannot be read: not an image, truncated, unsupported pixel format or absurd size."""


def _sixteen_bit(im) -> np.ndarray:
    """``[H, W, 3|4]`` float32 in ``[0, 1]`` from a 16-bit grayscale image (alpha from a ``tRNS`` value)."""
    raw = np.asarray(im).astype(np.int64)
    gray = (raw / 65535.0).astype(np.float32)
    channels = [gray, gray, gray]
    transparent = im.info.get("transparency")
    if isinstance(transparent, int):
        channels.append((raw != transparent).astype(np.float32))
    return np.stack(channels, axis=-1)


def _png_colour_key(im, path: Path) -> None:
    """Fix or reject the ``tRNS`` colour keys Pillow misreads (it keeps the raw key, not the pixels' scale)."""
    rawmode = im.tile[0][3] if im.format == "PNG" and "transparency" in im.info and im.tile else None
    if rawmode in ("L;2", "L;4"):  # pixels are scaled to 0..255, the key is not
        im.info["transparency"] = int(im.info["transparency"]) * (255 // (2 ** int(rawmode[-1]) - 1))
    elif rawmode in ("RGB;16B", "RGB;16"):
        raise ImageError(f"{path}: 16-bit RGB PNG with a tRNS colour key is not supported (Pillow keeps only "
                         "the top 8 bits of each sample, so the key cannot be matched)")


def read_image(path: str | os.PathLike, *, keep_uint8: bool = False) -> Tensor:
    """Reads an image file (Pillow) at its full range (see the module docstring for the pixel formats).

    Args:
        path: a PNG, JPEG or other Pillow-readable file.
        keep_uint8: return an 8-bit image without alpha as its ``[3, H, W]`` uint8 samples (0..255, a quarter
            of the memory; a channel-first view of the decoded ``[H, W, 3]`` array, not contiguous;
            :func:`to_unit` makes it the float32 result bitwise) -- for readers that hand images to a GPU.
            Images with alpha and 16-bit images still come back as float32.

    Returns:
        ``[C, H, W]`` float32 in ``[0, 1]`` (or uint8, see ``keep_uint8``); ``C = 4`` (RGBA, straight alpha)
        when the file has an alpha channel or ``tRNS`` transparency, else ``C = 3`` (grayscale is repeated
        over RGB).

    Raises:
        FileNotFoundError: the file does not exist.
        ImageError: the path is a directory, or the file cannot be decoded (not an image, truncated),
            has an unsupported pixel format, or is larger than ``MAX_IMAGE_SIZE`` on a side.
    """
    from PIL import Image  # noqa: PLC0415

    path = Path(path)
    if path.is_dir():
        raise ImageError(f"{path}: is a directory, not an image file")
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    try:
        with Image.open(path) as im:
            width, height = im.size
            if not (1 <= width <= MAX_IMAGE_SIZE and 1 <= height <= MAX_IMAGE_SIZE):
                raise ImageError(f"{path}: image is {width}x{height}; sides must be in 1..{MAX_IMAGE_SIZE} pixels")
            _png_colour_key(im, path)
            if im.mode in _SIXTEEN_BIT:
                arr = _sixteen_bit(im)
            elif im.mode in _EIGHT_BIT:
                has_alpha = im.mode in _ALPHA_MODES or "transparency" in im.info
                target = "RGBA" if has_alpha else "RGB"
                arr = np.asarray(im if im.mode == target else im.convert(target))  # no copy when already there
                if not arr.flags.writeable:  # torch wants writable memory
                    arr = arr.copy()
            else:
                raise ImageError(
                    f"{path}: unsupported pixel format (Pillow mode {im.mode!r}); supported: 8-bit modes "
                    f"{', '.join(_EIGHT_BIT)} and 16-bit grayscale"
                )
    except ImageError:
        raise
    except Exception as exc:  # decoder-specific exception types (UnidentifiedImageError, OSError, ...)
        raise ImageError(f"cannot decode image {path}: {exc}") from exc
    if arr.shape[:2] != (height, width):
        raise ImageError(f"cannot decode image {path}: decoded {arr.shape[:2]} pixels, header says {height}x{width}")
    chw = torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1)
    if chw.dtype != torch.uint8:
        return chw.contiguous()
    if keep_uint8 and chw.shape[0] == 3:  # a view of the decoded [H, W, 3] samples; .to(device) moves them as they are
        return chw
    return to_unit(chw.contiguous())  # the 8-bit samples made channel-first, then divided by 255 (one float pass)


def write_image(path: str | os.PathLike, image: Tensor, *, quality: int = 95) -> Path:
    """Writes a ``[3, H, W]`` or ``[4, H, W]`` float image in ``[0, 1]`` as 8 bits, atomically.

    Args:
        path: destination file; the format follows the suffix (``.png``, ``.jpg``, ...); its
            directory must exist.
        image: channel-major image (values are clamped to [0, 1] and rounded).
        quality: JPEG quality when writing a JPEG.

    Returns:
        The path written.
    """
    from PIL import Image  # noqa: PLC0415

    path = Path(path)
    if image.dim() != 3 or image.shape[0] not in (3, 4):
        raise ValueError(f"write_image expects [3|4, H, W], got {list(image.shape)}")
    if not torch.isfinite(image).all():
        raise ValueError("image contains NaN or Inf")
    fmt = Image.registered_extensions().get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"unknown image format for {path}")
    arr = (image.detach().float().cpu().clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy()
    with atomic_write(path, "wb") as f:
        Image.fromarray(np.ascontiguousarray(arr)).save(f, format=fmt, **({"quality": quality} if fmt == "JPEG" else {}))
    return path


def resize_image(image: Tensor, height: int, width: int) -> Tensor:
    """Resize ``[C, H, W]`` (or ``[B, C, H, W]``) to ``height x width``.

    Integer downscale factors use box (area) averaging, other sizes antialiased bilinear interpolation.
    """
    squeeze = image.dim() == 3
    x = image[None] if squeeze else image
    h, w = x.shape[-2:]
    if (h, w) == (height, width):
        out = x
    elif h % height == 0 and w % width == 0 and h // height == w // width:
        out = F.avg_pool2d(x, h // height)
    else:
        out = F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False, antialias=True)
    return out[0] if squeeze else out


def to_unit(image: Tensor) -> Tensor:
    """A float32 image in ``[0, 1]``: uint8 samples divided by 255 (bitwise :func:`read_image`'s float result, on
    any device: a tensor divisor, not the reciprocal CUDA multiplies by for a scalar one); float images
    converted to float32 and clamped to ``[0, 1]``.

    Args:
        image: ``[..., H, W]`` uint8 or floating-point.

    Returns:
        ``[..., H, W]`` float32 on the image's device.
    """
    if image.dtype == torch.uint8:
        return image.float() / constant(255.0, torch.float32, image.device)
    return image.float().clamp(0, 1)


def read_rgb(path: str | os.PathLike, *, keep_uint8: bool = False) -> Tensor:
    """A [3, H, W] image as the decoder reads it: :func:`read_image`, an alpha channel composited on black (as
    renders are; the result is then float32 in [0, 1]).

    Raises:
        FileNotFoundError / ImageError: as :func:`read_image`.
    """
    img = read_image(path, keep_uint8=keep_uint8)
    return composite(img, torch.zeros(3))[0] if img.shape[0] == 4 else img


def composite(rgba: Tensor, background: Tensor) -> tuple[Tensor, Tensor]:
    """Composite a straight-alpha ``[4, H, W]`` image on a background colour.

    Returns:
        ``rgb [3, H, W] = alpha * rgb + (1 - alpha) * background`` and ``alpha [1, H, W]``.
    """
    alpha = rgba[3:4]
    return rgba[:3] * alpha + (1.0 - alpha) * background.view(3, 1, 1).to(rgba), alpha
