"""Image file IO (Pillow, atomic writes) and resizing. Tensors are channel-major float32 in ``[0, 1]``."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from gsw._atomic import atomic_write

__all__ = ["read_image", "write_image", "resize_image", "composite", "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


def read_image(path: str | os.PathLike) -> Tensor:
    """Reads an image file (Pillow).

    Args:
        path: a PNG, JPEG or other Pillow-readable file.

    Returns:
        ``[C, H, W]`` float32 in ``[0, 1]``; ``C = 4`` when the file has an alpha channel, else 3.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file cannot be decoded.
    """
    from PIL import Image  # noqa: PLC0415

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    try:
        with Image.open(path) as im:
            has_alpha = im.mode in ("RGBA", "LA", "PA") or "transparency" in im.info
            arr = np.array(im.convert("RGBA" if has_alpha else "RGB"), dtype=np.uint8, order="C")
    except Exception as exc:  # decoder-specific exception types
        raise ValueError(f"cannot decode image {path}: {exc}") from exc
    return torch.from_numpy(arr).permute(2, 0, 1).float().div_(255.0)


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


def composite(rgba: Tensor, background: Tensor) -> tuple[Tensor, Tensor]:
    """Composite a straight-alpha ``[4, H, W]`` image on a background colour.

    Returns:
        ``rgb [3, H, W] = alpha * rgb + (1 - alpha) * background`` and ``alpha [1, H, W]``.
    """
    alpha = rgba[3:4]
    return rgba[:3] * alpha + (1.0 - alpha) * background.view(3, 1, 1).to(rgba), alpha
