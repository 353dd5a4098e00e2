"""Image files <-> tensors (Pillow), with atomic writes.

Tensors are channel-major float images in [0, 1]: `[C, H, W]` with C = 3 (RGB) or 4 (RGBA).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from gsw._atomic import atomic_write


def read_image(path: str | os.PathLike) -> Tensor:
    """Reads an image file.

    Args:
        path: a PNG/JPEG/... file.

    Returns:
        [C, H, W] float32 in [0, 1]; C = 4 when the file has an alpha channel, else 3.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable image.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    try:
        with Image.open(path) as im:
            has_alpha = im.mode in ("RGBA", "LA", "PA") or "transparency" in im.info
            arr = np.asarray(im.convert("RGBA" if has_alpha else "RGB"))
    except (UnidentifiedImageError, OSError) as err:
        raise ValueError(f"not a readable image: {path} ({err})") from err
    return torch.from_numpy(arr.copy()).permute(2, 0, 1).float().div_(255.0)


def to_uint8(image: Tensor) -> np.ndarray:
    """[C, H, W] or [H, W, C] float image in [0, 1] -> [H, W, C] uint8 (rounded, clamped)."""
    if image.dim() != 3:
        raise ValueError(f"expected a [C,H,W] or [H,W,C] image, got shape {list(image.shape)}")
    img = image.detach().float().cpu()
    if img.shape[0] in (1, 3, 4):  # channel-major (the library's convention) wins
        img = img.permute(1, 2, 0)
    elif img.shape[-1] not in (1, 3, 4):
        raise ValueError(f"expected 1, 3 or 4 channels, got shape {list(image.shape)}")
    if not torch.isfinite(img).all():
        raise ValueError("image contains NaN or Inf")
    return (img.clamp(0, 1) * 255.0).round().to(torch.uint8).numpy()


def write_image(path: str | os.PathLike, image: Tensor, *, quality: int = 95) -> Path:
    """Writes an image atomically (format from the suffix: .png, .jpg, ...).

    Args:
        path: destination file; its directory must exist.
        image: [3, H, W] / [4, H, W] (or [H, W, C]) float in [0, 1].
        quality: JPEG quality when writing a JPEG.

    Returns:
        The written path.
    """
    from PIL import Image

    path = Path(path)
    arr = to_uint8(image)
    im = Image.fromarray(arr[..., 0] if arr.shape[-1] == 1 else arr)
    fmt = Image.registered_extensions().get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"unknown image format for {path}")
    with atomic_write(path, "wb") as f:
        im.save(f, format=fmt, **({"quality": quality} if fmt == "JPEG" else {}))
    return path
