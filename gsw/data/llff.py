"""LLFF datasets: ``poses_bounds.npy`` + ``images/`` (or ``images_N/``), as used by NeRF's forward-facing scenes.

``poses_bounds.npy`` is a float ``[N, 17]`` array, one row per image in sorted file-name order: 15 values of a
row-major ``[3, 5]`` matrix ``[c2w (3 x 4) | (H, W, focal)]``, then the near and far depth bounds. The
camera-to-world rotation columns are LLFF's ``(down, right, backward)`` axes and column 3 the camera centre;
in OpenCV axes (:mod:`gsw.camera`) the camera's right, down and forward directions are columns 1, 0 and -2.
``H, W, focal`` describe the full-resolution images; the principal point is the image centre. Images of
another size (``images_N``) get their intrinsics scaled by the actual size ratios.

Example:
    >>> from gsw.data.llff import load_llff
    >>> ds = load_llff("fern", "test", downscale=8)  # doctest: +SKIP
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from gsw.camera import Camera
from gsw.data._posed import PosedView, image_folder, load_views
from gsw.data.distortion import Distortion
from gsw.data.images import IMAGE_SUFFIXES
from gsw.data.loaders import Background, Dataset, DatasetError, _background, _check_downscale, holdout_indices

__all__ = ["load_llff", "llff_cameras", "LLFF_TO_OPENGL"]

#: Column map from LLFF ``(down, right, backward)`` to OpenGL ``(right, up, backward)`` axes: new column j is
#: ``sign * old column``.
LLFF_TO_OPENGL = ((1, 1.0), (0, -1.0), (2, 1.0))


def llff_cameras(poses_bounds: np.ndarray, source: str = "poses_bounds.npy") -> tuple[list[Camera], np.ndarray]:
    """Cameras and depth bounds of a ``poses_bounds`` array.

    Args:
        poses_bounds: ``[N, 17]`` array.
        source: name for error messages.

    Returns:
        ``N`` cameras at the stated full resolution (centred principal point, ``fx = fy = focal``) and the
        ``[N, 2]`` near/far bounds.

    Raises:
        DatasetError: wrong shape, non-finite values, a non-positive size or focal, a non-rigid rotation.
    """
    arr = np.asarray(poses_bounds, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise DatasetError(f"{source}: expected an [N, 17] array, got shape {list(arr.shape)}")
    if not np.isfinite(arr).all():
        raise DatasetError(f"{source}: non-finite values")
    poses = arr[:, :15].reshape(-1, 3, 5)
    cameras = []
    for i, pose in enumerate(poses):
        height, width, focal = pose[:, 4]
        if height < 1 or width < 1 or focal <= 0 or height != round(height) or width != round(width):
            raise DatasetError(f"{source}: row {i}: bad image size / focal (H={height}, W={width}, f={focal})")
        c2w = np.eye(4)
        for j, (col, sign) in enumerate(LLFF_TO_OPENGL):
            c2w[:3, j] = sign * pose[:, col]
        c2w[:3, 3] = pose[:, 3]
        r = c2w[:3, :3]
        if np.abs(r @ r.T - np.eye(3)).max() > 1e-4 or np.linalg.det(r) < 0:
            raise DatasetError(f"{source}: row {i}: the rotation is not orthonormal / right-handed")
        try:
            cameras.append(Camera.from_nerf(torch.from_numpy(c2w), int(width), int(height), fx=float(focal)))
        except ValueError as exc:
            raise DatasetError(f"{source}: row {i}: {exc}") from None
    return cameras, arr[:, 15:17].copy()


def load_llff(root: str | os.PathLike, split: str = "train", *, downscale: float = 1,
              background: Background = (1.0, 1.0, 1.0), holdout_every: int = 8,
              images_dir: str | os.PathLike | None = None) -> Dataset:
    """Load an LLFF scene folder (``poses_bounds.npy`` and ``images/``).

    Args:
        root: the scene folder.
        split: ``"all"``, or ``"train"`` / ``"test"`` (``"val"`` = test) holding out every
            ``holdout_every``-th image (NeRF's ``llffhold``).
        downscale: image size divisor (>= 1); an integer ``N`` reads ``root/images_N`` when it exists.
        background: RGB for images with alpha.
        holdout_every: hold-out period of ``split``.
        images_dir: read the images from this folder instead (resized to ``1 / downscale``).

    Returns:
        The :class:`~gsw.data.loaders.Dataset` (``format = "llff"``; ``meta["bounds"]`` is the ``[V, 2]``
        float64 near/far depths of the loaded views).

    Raises:
        DatasetError: missing or malformed ``poses_bounds.npy``, a number of images different from its rows,
            missing images.
    """
    root = Path(root)
    downscale = _check_downscale(downscale)
    if split not in ("all", "train", "test", "val"):
        raise ValueError(f"split must be 'all', 'train', 'test' or 'val', got {split!r}")
    path = root / "poses_bounds.npy"
    if not path.is_file():
        raise DatasetError(f"missing file: {path}")
    try:
        data = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise DatasetError(f"{path}: not a readable .npy array ({exc})") from None
    cameras, bounds = llff_cameras(data, str(path))
    folder, remaining = image_folder(root, images_dir, downscale)
    if not folder.is_dir():
        raise DatasetError(f"images folder not found: {folder}")
    files = sorted(p for p in folder.iterdir() if p.suffix in IMAGE_SUFFIXES and p.is_file())
    if len(files) != len(cameras):
        raise DatasetError(f"{folder}: {len(files)} images but {path.name} has {len(cameras)} poses")
    index = list(range(len(cameras)))
    if split != "all":
        train_idx, test_idx = holdout_indices(len(index), holdout_every)
        index = train_idx if split == "train" else test_idx
    views = [PosedView(replace(cameras[i], name=files[i].name), Distortion(), files[i]) for i in index]
    cams, images, alphas = load_views(views, downscale=remaining, background=_background(background),
                                      undistort=False, source=str(path))
    return Dataset(cameras=cams, images=images, alphas=alphas, names=[c.name for c in cams],
                   background=_background(background),
                   format="llff", meta={"bounds": bounds[index], "images_dir": str(folder), "split": split})
