"""Image file IO and resizing for the dataset loaders.

Decoding uses Pillow when it is importable and otherwise ``kornia_rs`` (the Rust image codecs that ship with
kornia, a dependency of the package), so PNG/JPEG loading works in either environment. Tensors are channel-major
float32 in ``[0, 1]``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from gsw._atomic import atomic_write

__all__ = ["read_image", "write_png", "resize_image", "composite", "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


def _read_pil(path: Path) -> np.ndarray:
    from PIL import Image  # noqa: PLC0415

    with Image.open(path) as im:
        has_alpha = im.mode in ("RGBA", "LA", "PA") or "transparency" in im.info
        return np.asarray(im.convert("RGBA" if has_alpha else "RGB"))


def _read_kornia_rs(path: Path) -> np.ndarray:
    import kornia_rs  # noqa: PLC0415

    arr = np.asarray(kornia_rs.read_image(str(path)))
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.dtype == np.uint16:  # 16-bit PNG
        arr = (arr.astype(np.float32) / 257.0).round().astype(np.uint8)
    if arr.shape[-1] == 1:
        arr = np.repeat(arr, 3, axis=-1)
    elif arr.shape[-1] == 2:  # gray + alpha
        arr = np.concatenate([np.repeat(arr[..., :1], 3, axis=-1), arr[..., 1:]], axis=-1)
    return arr


def read_image(path: str | os.PathLike) -> Tensor:
    """Read an image file.

    Args:
        path: a PNG or JPEG file.

    Returns:
        ``[C, H, W]`` float32 in ``[0, 1]``; ``C = 4`` when the file has an alpha channel, else 3.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file cannot be decoded.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    try:
        import PIL  # noqa: F401, PLC0415

        reader = _read_pil
    except ImportError:
        reader = _read_kornia_rs
    try:
        arr = reader(path)
    except Exception as exc:  # decoder-specific exception types
        raise ValueError(f"cannot decode image {path}: {exc}") from exc
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[-1] not in (3, 4):
        raise ValueError(f"unsupported image layout in {path}: shape {arr.shape}, dtype {arr.dtype}")
    arr = np.array(arr, dtype=np.uint8, copy=True, order="C")
    return torch.from_numpy(arr).permute(2, 0, 1).float().div_(255.0)


def write_png(path: str | os.PathLike, image: Tensor) -> Path:
    """Write a ``[3, H, W]`` or ``[4, H, W]`` float image in ``[0, 1]`` as an 8-bit PNG, atomically.

    Args:
        path: destination ``.png`` file (its directory must exist).
        image: channel-major image.

    Returns:
        The path written.
    """
    path = Path(path)
    if image.dim() != 3 or image.shape[0] not in (3, 4):
        raise ValueError(f"write_png expects [3|4, H, W], got {list(image.shape)}")
    arr = (image.detach().float().cpu().clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy()
    arr = np.ascontiguousarray(arr)
    try:
        from PIL import Image  # noqa: PLC0415

        with atomic_write(path, "wb") as f:
            Image.fromarray(arr).save(f, format="PNG")
    except ImportError:
        import kornia_rs  # noqa: PLC0415

        tmp = path.with_name(f".{path.name}.tmp.png")
        kornia_rs.write_image_png_u8(str(tmp), arr, "rgba" if arr.shape[-1] == 4 else "rgb")
        os.replace(tmp, path)
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
