"""COLMAP datasets: a sparse model (``sparse/0/`` or ``sparse/``, binary or text) and ``images/`` (or
``images_N/``), the input of INRIA 3DGS, gsplat and nerfstudio.

Cameras: COLMAP stores world-to-camera poses in OpenCV axes and intrinsics with the image spanning ``[0, W]``
(pixel centres at ``+0.5``), the :mod:`gsw.camera` conventions, so poses and ``fx, fy, cx, cy`` are used as
stored. Supported camera models and their parameters::

    SIMPLE_PINHOLE  f, cx, cy                   PINHOLE  fx, fy, cx, cy
    SIMPLE_RADIAL   f, cx, cy, k                RADIAL   f, cx, cy, k1, k2
    OPENCV          fx, fy, cx, cy, k1, k2, p1, p2

The radial-tangential models are resampled into pinhole cameras with the same intrinsics
(:func:`gsw.data.distortion.undistort_image`); fisheye and the other models are rejected.

Example:
    >>> from gsw.data.colmap import load_colmap
    >>> ds = load_colmap("garden", "train", downscale=4)  # reads garden/images_4 when present  # doctest: +SKIP
"""

from __future__ import annotations

import os
from pathlib import Path
import torch

from gsw.camera import Camera
from gsw.data._posed import PosedView, image_folder, load_views
from gsw.data.colmap_io import ColmapCamera, ColmapError, ColmapImage, ColmapModel, find_colmap_model, \
    read_colmap_model
from gsw.data.distortion import Distortion
from gsw.data.loaders import Background, Dataset, DatasetError, _background, _check_downscale, holdout_indices
from gsw.gaussians import quat_to_rotmat, rotmat_to_quat

__all__ = ["load_colmap", "colmap_cameras", "colmap_camera", "camera_to_colmap", "SUPPORTED_CAMERA_MODELS"]

SUPPORTED_CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
"""COLMAP camera models :func:`colmap_camera` converts."""


def _intrinsics(cam: ColmapCamera) -> tuple[float, float, float, float, Distortion]:
    p = cam.params
    if cam.model == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2], Distortion()
    if cam.model == "PINHOLE":
        return p[0], p[1], p[2], p[3], Distortion()
    if cam.model == "SIMPLE_RADIAL":
        return p[0], p[0], p[1], p[2], Distortion(k1=p[3])
    if cam.model == "RADIAL":
        return p[0], p[0], p[1], p[2], Distortion(k1=p[3], k2=p[4])
    if cam.model == "OPENCV":
        return p[0], p[1], p[2], p[3], Distortion(k1=p[4], k2=p[5], p1=p[6], p2=p[7])
    raise ColmapError(f"COLMAP camera {cam.camera_id}: model {cam.model} is not supported "
                      f"(supported: {', '.join(SUPPORTED_CAMERA_MODELS)})")


def colmap_camera(image: ColmapImage, camera: ColmapCamera) -> tuple[Camera, Distortion]:
    """The :class:`~gsw.camera.Camera` (at the model's resolution) and lens distortion of one image.

    Raises:
        ColmapError: an unsupported camera model or a degenerate pose.
    """
    fx, fy, cx, cy, distortion = _intrinsics(camera)
    viewmat = torch.eye(4, dtype=torch.float64)
    if not any(image.qvec):
        raise ColmapError(f"image {image.name!r}: zero rotation quaternion")
    viewmat[:3, :3] = quat_to_rotmat(torch.tensor(image.qvec, dtype=torch.float64))
    viewmat[:3, 3] = torch.tensor(image.tvec, dtype=torch.float64)
    try:
        cam = Camera(viewmat=viewmat, fx=fx, fy=fy, cx=cx, cy=cy, width=int(camera.width),
                     height=int(camera.height), name=image.name)
    except ValueError as exc:
        raise ColmapError(f"image {image.name!r}: {exc}") from None
    return cam, distortion


def colmap_cameras(model: ColmapModel) -> list[tuple[Camera, Distortion]]:
    """Every image's camera and distortion, sorted by image name (INRIA's order)."""
    return [colmap_camera(im, model.cameras[im.camera_id]) for im in sorted(model.images, key=lambda i: i.name)]


def camera_to_colmap(camera: Camera, image_id: int, camera_id: int) -> tuple[ColmapImage, ColmapCamera]:
    """A :class:`~gsw.camera.Camera` as a COLMAP ``PINHOLE`` camera and image entry (inverse of
    :func:`colmap_camera` for pinhole cameras)."""
    v = camera.viewmat.detach().double().cpu()
    q = rotmat_to_quat(v[:3, :3]).tolist()
    image = ColmapImage(image_id, tuple(q), tuple(v[:3, 3].tolist()), camera_id, camera.name)
    cam = ColmapCamera(camera_id, "PINHOLE", camera.width, camera.height, (camera.fx, camera.fy, camera.cx,
                                                                           camera.cy))
    return image, cam


def load_colmap(root: str | os.PathLike, split: str = "train", *, downscale: float = 1,
                background: Background = (1.0, 1.0, 1.0), holdout_every: int = 8, undistort: bool = True,
                images_dir: str | os.PathLike | None = None) -> Dataset:
    """Load a COLMAP dataset folder.

    Args:
        root: the scene folder holding ``sparse/0/`` (or ``sparse/``, or the model files themselves) and
            ``images/``.
        split: ``"all"``, or ``"train"`` / ``"test"`` (``"val"`` = test): every ``holdout_every``-th image in
            name order is held out (INRIA's ``llffhold`` split).
        downscale: image size divisor (>= 1). An integer ``N`` reads ``root/images_N`` when it exists (the
            usual pre-downscaled copies), else resizes ``root/images``.
        background: RGB the images are composited on when they have alpha.
        holdout_every: hold-out period of ``split``.
        undistort: resample distorted cameras into pinhole ones (else raise on distortion).
        images_dir: read the images from this folder instead (resized to ``1 / downscale``).

    Returns:
        The :class:`~gsw.data.loaders.Dataset` (``format = "colmap"``, ``points``/``point_colors`` from
        ``points3D``, ``meta`` with ``sparse`` (the model folder), ``images_dir``, ``camera_models``, ``split``).

    Raises:
        DatasetError: no sparse model, malformed files, unsupported camera models, missing images.
    """
    root = Path(root)
    downscale = _check_downscale(downscale)
    if split not in ("all", "train", "test", "val"):
        raise ValueError(f"split must be 'all', 'train', 'test' or 'val', got {split!r}")
    sparse = find_colmap_model(root)
    if sparse is None:
        raise DatasetError(f"{root}: no COLMAP model (cameras.bin/.txt in {root}, {root}/sparse/0 or {root}/sparse)")
    try:
        model = read_colmap_model(sparse)
        views = colmap_cameras(model)
    except ColmapError as exc:
        raise DatasetError(str(exc)) from None
    folder, remaining = image_folder(root, images_dir, downscale)
    if not folder.is_dir():
        raise DatasetError(f"images folder not found: {folder}")
    names = sorted(model.images, key=lambda i: i.name)
    index = list(range(len(views)))
    if split != "all":
        train_idx, test_idx = holdout_indices(len(index), holdout_every)
        index = train_idx if split == "train" else test_idx
    posed = [PosedView(views[i][0], views[i][1], folder / names[i].name) for i in index]
    cameras, images, alphas = load_views(posed, downscale=remaining, background=_background(background),
                                         undistort=undistort, source=str(sparse))
    return Dataset(cameras=cameras, images=images, alphas=alphas, names=[c.name for c in cameras],
                   background=_background(background), format="colmap",
                   points=torch.from_numpy(model.points).float(),
                   point_colors=torch.from_numpy(model.colors).float() / 255.0,
                   meta={"sparse": str(sparse), "images_dir": str(folder), "split": split,
                         "camera_models": sorted({c.model for c in model.cameras.values()})})
