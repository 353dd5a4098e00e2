"""Training photos: loading, random crops on the host, and the device-resident image bank.

The pre-training data is a folder of photos with ``train/`` and ``val/`` sub-folders (bsds500:
200 + 100 JPEGs of 481 x 321 or 321 x 481 pixels).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["IMAGE_SUFFIXES", "bank_crops", "image_bank", "load_images", "load_split", "photo_paths", "random_crops"]

#: File suffixes read as photos (case-insensitive).
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


def _read_image(path: Path) -> np.ndarray:
    """One photo as uint8 [H,W,3]: JPEGs through kornia_rs (libjpeg-turbo) when installed, the rest (and JPEGs
    without kornia_rs) through Pillow, alpha dropped."""
    if path.suffix.lower() in (".jpg", ".jpeg"):
        try:
            import kornia_rs

            return np.asarray(kornia_rs.read_image_jpeg(str(path), "rgb"))
        except ImportError:
            pass
    from PIL import Image

    with Image.open(path) as im:
        return np.array(im.convert("RGB"))


def photo_paths(folder: str | Path) -> list[Path]:
    """The .jpg/.jpeg/.png files of ``folder`` in file-name order.

    Raises:
        FileNotFoundError: ``folder`` does not exist or holds no photo.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"photo folder not found: {folder}")
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not paths:
        raise FileNotFoundError(f"no images in {folder}")
    return paths


def load_images(folder: str | Path, limit: int | None = None) -> list[torch.Tensor]:
    """The photos of ``folder`` (:func:`photo_paths`) as uint8 tensors [3,H,W].

    Args:
        folder: the folder to read.
        limit: read only the first ``limit`` photos.

    Raises:
        FileNotFoundError: ``folder`` does not exist or holds no photo.
    """
    paths = photo_paths(folder)[:limit]
    return [torch.from_numpy(np.ascontiguousarray(_read_image(p))).permute(2, 0, 1).contiguous() for p in paths]


def load_split(data: str | Path, split: str, limit: int | None = None) -> list[torch.Tensor]:
    """The photos of ``data/split`` (``split`` is ``"train"`` or ``"val"``), see :func:`load_images`."""
    return load_images(Path(data) / split, limit)


def random_crops(
    images: list[torch.Tensor], n: int, size: int, generator: torch.Generator, device: torch.device | str
) -> torch.Tensor:
    """n random ``size`` x ``size`` crops with random horizontal flips, float [n,3,size,size] in [0,1].

    Photos smaller than ``size`` are first enlarged (bilinear) to at least ``size`` on each side.
    """
    idx = torch.randint(len(images), (n,), generator=generator).tolist()
    u = torch.rand(n, 3, generator=generator)
    out = []
    for i, k in enumerate(idx):
        img = images[k]
        h, w = img.shape[-2:]
        if h < size or w < size:
            img = F.interpolate(img[None].float(), size=(max(h, size), max(w, size)), mode="bilinear")[0]
            h, w = img.shape[-2:]
        y, x = int(u[i, 0] * (h - size + 1)), int(u[i, 1] * (w - size + 1))
        c = img[:, y : y + size, x : x + size]
        out.append(c.flip(-1) if u[i, 2] < 0.5 else c)
    return torch.stack(out).to(device, non_blocking=True).float() / 255.0


def image_bank(images: list[torch.Tensor], device: torch.device | str) -> torch.Tensor:
    """uint8 [N,3,H,W] on ``device``: portrait photos transposed to landscape, all cropped (centre) to the
    smallest common size."""
    ims = [img if img.shape[-2] <= img.shape[-1] else img.transpose(-1, -2) for img in images]
    h = min(i.shape[-2] for i in ims)
    w = min(i.shape[-1] for i in ims)
    out = []
    for i in ims:
        y0, x0 = (i.shape[-2] - h) // 2, (i.shape[-1] - w) // 2
        out.append(i[:, y0 : y0 + h, x0 : x0 + w])
    return torch.stack(out).contiguous().to(device)


def bank_crops(bank: torch.Tensor, n: int, size: int, gen: torch.Generator,
               channels_last: bool = False) -> torch.Tensor:
    """n random ``size`` x ``size`` crops of ``bank`` [N,3,H,W] (uint8) with random horizontal and vertical
    flips, one gather; float [n,3,size,size] in [0,1] on the bank's device."""
    dev = bank.device
    N, _, H, W = bank.shape
    u = torch.rand(n, 5, device=dev, generator=gen)
    k = (u[:, 0] * N).long().clamp_max(N - 1)
    oy = (u[:, 1] * (H - size + 1)).long().clamp_max(H - size)
    ox = (u[:, 2] * (W - size + 1)).long().clamp_max(W - size)
    ar = torch.arange(size, device=dev)
    ry = oy[:, None] + torch.where(u[:, 3:4] < 0.5, ar, size - 1 - ar)  # vertical flip
    rx = ox[:, None] + torch.where(u[:, 4:5] < 0.5, ar, size - 1 - ar)  # horizontal flip
    c = bank[k[:, None, None], :, ry[:, :, None], rx[:, None, :]]  # [n,size,size,3] (NHWC)
    x = c.permute(0, 3, 1, 2).float() / 255.0
    return x.contiguous(memory_format=torch.channels_last) if channels_last else x.contiguous()
