"""INRIA 3DGS model folders: ``point_cloud/iteration_*/point_cloud.ply`` + ``cameras.json`` (+ source images).

Source images must have their camera's size in ``cameras.json``; they are resized only by an explicit
``downscale`` or, for photos at a uniform multiple of the training resolution, ``resize_images=True``.
"""

from __future__ import annotations

import os
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple, Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.camera_io import CameraFileError, load_inria_cameras, save_inria_cameras
from gsw.data.dataset import Background, DatasetError, _background, _check_downscale, _check_usable, \
    _find_images, _read_view
from gsw.data.images import composite, resize_image
from gsw.gaussians import Gaussians

__all__ = ["InriaModel", "READ_THREADS", "load_inria_model", "save_inria_model"]

#: Threads decoding a model folder's source images.
READ_THREADS = 8


class InriaModel(NamedTuple):
    """What :func:`load_inria_model` returns; ``resized`` names the source images resampled to their camera's
    size (``resize_images=True``)."""

    gaussians: Gaussians
    cameras: list[Camera]
    images: Tensor | None
    iteration: int
    folder: Path
    resized: tuple[str, ...] = ()


def save_inria_model(folder: str | os.PathLike, gaussians: Gaussians, cameras: Sequence[Camera],
                     iteration: int) -> Path:
    """Write an INRIA model folder: ``point_cloud/iteration_{iteration}/point_cloud.ply`` + ``cameras.json``.

    Both files are written atomically (temporary file + rename). Returns the PLY path.
    """
    from gsw.io.ply import save_ply  # noqa: PLC0415

    folder = Path(folder)
    ply_dir = folder / "point_cloud" / f"iteration_{int(iteration)}"
    ply_dir.mkdir(parents=True, exist_ok=True)
    ply = ply_dir / "point_cloud.ply"
    save_ply(gaussians, ply)
    save_inria_cameras(cameras, folder / "cameras.json")
    return ply


_ITER_RE = re.compile(r"^iteration_(\d+)$")


def load_inria_model(folder: str | os.PathLike, *, iteration: int | None = None,
                     images_dir: str | os.PathLike | None = None, downscale: float = 1,
                     background: Background = (1.0, 1.0, 1.0), resize_images: bool = False) -> InriaModel:
    """Load an INRIA 3DGS output folder: ``point_cloud/iteration_*/point_cloud.ply`` + ``cameras.json``.

    Args:
        folder: the model folder.
        iteration: which ``iteration_N`` to load (default: the largest).
        images_dir: optional folder with the source images, matched by ``img_name`` (with or without an
            extension). Each must have its camera's size in ``cameras.json`` (then ``downscale`` applies to
            both); any other size is an error unless ``resize_images``.
        downscale: extra size divisor applied to cameras and images (>= 1).
        background: RGB for RGBA source images.
        resize_images: resample source images whose size is a uniform multiple of their camera's (INRIA
            stores its training resolution in ``cameras.json``, so full-size photos differ from it).

    Returns:
        :class:`InriaModel` ``(gaussians, cameras, images or None, iteration, folder)``.

    Raises:
        DatasetError: a missing folder/file, a malformed ``cameras.json`` (the camera index and field
            named), missing images (all named), an image size that does not match its camera, or a view
            smaller than :data:`MIN_IMAGE_SIZE`.
        gsw.io.PlyError: a malformed PLY.
    """
    from gsw.io.ply import load_ply  # noqa: PLC0415

    folder = Path(folder)
    downscale = _check_downscale(downscale)
    ply, iteration = _inria_ply(folder, iteration)
    gaussians = load_ply(ply)
    try:
        cameras = load_inria_cameras(folder / "cameras.json")
    except CameraFileError as exc:
        raise DatasetError(str(exc)) from None
    images, resized = None, ()
    if images_dir is not None:
        images, resized = _load_named_images(Path(images_dir), cameras, downscale, _background(background),
                                             resize_images)
    if downscale != 1.0:
        cameras = [c.scaled(1.0 / downscale) for c in cameras]
    return InriaModel(gaussians, cameras, images, iteration, folder, resized)


def _inria_ply(folder: Path, iteration: int | None) -> tuple[Path, int]:
    """``point_cloud/iteration_N/point_cloud.ply`` of the requested (default: largest) iteration."""
    if not folder.is_dir():
        raise DatasetError(f"model folder not found: {folder}")
    pc = folder / "point_cloud"
    iterations = sorted(int(m.group(1)) for d in (pc.iterdir() if pc.is_dir() else [])
                        if d.is_dir() and (m := _ITER_RE.match(d.name)))
    if not iterations:
        raise DatasetError(f"{folder}: no point_cloud/iteration_*/ folder (not an INRIA model folder)")
    if iteration is None:
        iteration = iterations[-1]
    elif iteration not in iterations:
        raise DatasetError(f"{folder}: no iteration {iteration} (available: {iterations})")
    ply = pc / f"iteration_{iteration}" / "point_cloud.ply"
    if not ply.is_file():
        raise DatasetError(f"missing file: {ply}")
    return ply, iteration


def _load_named_images(images_dir: Path, cameras: Sequence[Camera], downscale: float, bg: Tensor,
                       resize_images: bool) -> tuple[Tensor, tuple[str, ...]]:
    """``[V, 3, H, W]`` source images matched to ``cameras`` (their ``cameras.json`` size) by name, and the names
    of those resampled from another size."""
    if not images_dir.is_dir():
        raise DatasetError(f"images folder not found: {images_dir}")
    unnamed = [k for k, cam in enumerate(cameras) if not cam.name]
    if unnamed:
        raise DatasetError(f"cameras {unnamed[:10]} have no img_name; cannot match them to image files")
    paths = _find_images(images_dir, [cam.name for cam in cameras], f"images for cameras.json in {images_dir}")
    out, resized = [], []
    contexts = [f"camera {k} ({cam.name!r})" for k, cam in enumerate(cameras)]
    with ThreadPoolExecutor(max_workers=min(READ_THREADS, max(1, len(paths)))) as pool:
        # files decoded on threads (Pillow releases the GIL), checked in order: the first bad view is named
        for cam, path, ctx, img in zip(cameras, paths, contexts, pool.map(_read_view, paths, contexts)):
            out.append(_checked_view(img, cam, path, ctx, bg, downscale, resize_images, resized))
    return torch.stack(out).contiguous(), tuple(resized)


def _checked_view(img: Tensor, cam: Camera, path: Path, ctx: str, bg: Tensor, downscale: float,
                  resize_images: bool, resized: list[str]) -> Tensor:
    """One source image composited on ``bg``, checked against its camera and resized to it (its name appended
    to ``resized`` when resampled from another size)."""
    rgb = composite(img, bg)[0] if img.shape[0] == 4 else img
    h, w = rgb.shape[-2:]
    if (h, w) != (cam.height, cam.width):
        fx, fy = w / cam.width, h / cam.height
        if not resize_images or abs(fx - fy) > 0.02 * max(fx, fy):
            raise DatasetError(
                f"{path}: image is {w}x{h} but {ctx} in cameras.json is {cam.width}x{cam.height}"
                + ("" if resize_images else "; pass resize_images=True (gsw commands: --resize-images) to "
                   "resample images whose size is a uniform multiple of their camera's (INRIA stores its "
                   "training resolution)"))
        resized.append(path.name)
    target = cam.scaled(1.0 / downscale) if downscale != 1.0 else cam
    _check_usable(target.width, target.height, f"{path}")
    return resize_image(rgb, target.height, target.width)
