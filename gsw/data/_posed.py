"""Shared by the COLMAP and LLFF loaders: the image folder to read, and images matched to their cameras."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import NamedTuple, Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.data.distortion import Distortion, undistort_image
from gsw.data.images import composite, read_image, resize_image
from gsw.data.loaders import DatasetError

__all__ = ["PosedView", "image_folder", "load_views", "fit_camera"]

#: Largest relative difference of the x and y resize factors accepted between a camera and its image.
_ASPECT_TOL = 0.02


class PosedView(NamedTuple):
    """A camera at the resolution its model states, its lens distortion and its image file."""

    camera: Camera
    distortion: Distortion
    path: Path


def image_folder(root: Path, images_dir: str | Path | None, downscale: float) -> tuple[Path, float]:
    """The folder to read and the resize still to apply: ``images_dir`` if given, else ``root/images_N`` for an
    integer ``downscale = N`` when that folder exists (already downscaled), else ``root/images``."""
    if images_dir is not None:
        return Path(images_dir), downscale
    if downscale > 1 and downscale == int(downscale) and (root / f"images_{int(downscale)}").is_dir():
        return root / f"images_{int(downscale)}", 1.0
    return root / "images", downscale


def fit_camera(camera: Camera, width: int, height: int, context: str) -> Camera:
    """The camera for its image resized to ``width x height`` (intrinsics scaled by the size ratios).

    Raises:
        DatasetError: the new size is not a uniform rescale (x and y factors differ by more than 2 %).
    """
    if (width, height) == (camera.width, camera.height):
        return camera
    sx, sy = width / camera.width, height / camera.height
    if abs(sx - sy) > _ASPECT_TOL * max(sx, sy):
        raise DatasetError(f"{context}: the image is {width}x{height}, which is not a uniform rescale of the "
                           f"camera's {camera.width}x{camera.height}")
    return replace(camera, fx=camera.fx * sx, fy=camera.fy * sy, cx=camera.cx * sx, cy=camera.cy * sy,
                   width=width, height=height)


def load_views(views: Sequence[PosedView], *, downscale: float, background: Tensor, undistort: bool,
               source: str) -> tuple[list[Camera], Tensor, Tensor | None]:
    """Reads the images, fits each camera to its image, resizes by ``downscale``, undistorts, composites alpha.

    Returns:
        ``(cameras, images [V, 3, H, W], alphas [V, 1, H, W] or None)``.

    Raises:
        DatasetError: a missing or undecodable image, a non-uniform rescale, distortion with
            ``undistort=False``, or images of different sizes.
    """
    cameras, images, alphas = [], [], []
    any_alpha = False
    for view in views:
        context = f"{source}: {view.path.name}"
        if not view.path.is_file():
            raise DatasetError(f"{source}: image not found: {view.path}")
        try:
            img = read_image(view.path)
        except ValueError as exc:
            raise DatasetError(f"{context}: {exc}") from None
        cam = fit_camera(view.camera, img.shape[-1], img.shape[-2], context)
        if downscale != 1.0:
            cam = fit_camera(cam, max(1, round(cam.width / downscale)), max(1, round(cam.height / downscale)),
                             context)
            img = resize_image(img, cam.height, cam.width)
        d = view.distortion
        if not d.is_identity:
            if not undistort:
                raise DatasetError(f"{context}: the camera has lens distortion ({d}) and undistort=False; pass "
                                   "undistort=True to resample the images into pinhole cameras")
            img = undistort_image(img, cam.fx, cam.fy, cam.cx, cam.cy, d)
        if img.shape[0] == 4:
            any_alpha = True
            rgb, alpha = composite(img, background)
        else:
            rgb, alpha = img, torch.ones_like(img[:1])
        if images and rgb.shape != images[0].shape:
            raise DatasetError(f"{source}: images of different sizes ({view.path.name} is "
                               f"{rgb.shape[-1]}x{rgb.shape[-2]}, earlier ones "
                               f"{images[0].shape[-1]}x{images[0].shape[-2]})")
        cameras.append(cam)
        images.append(rgb)
        alphas.append(alpha)
    if not cameras:
        raise DatasetError(f"{source}: no images")
    return cameras, torch.stack(images).contiguous(), torch.stack(alphas).contiguous() if any_alpha else None
