"""nerfstudio datasets (``ns-process-data`` output: ``transforms.json`` + images) and the normalised frame of
models trained on them (splatfacto, gsplat's nerfstudio parser).

``transforms.json`` is instant-ngp's layout (camera-to-world ``transform_matrix`` in OpenGL axes, ``fl_x, fl_y,
cx, cy, w, h``, OpenCV ``k1, k2, p1, p2`` distortion) plus ``camera_model`` and optionally ``applied_transform``
(``[3, 4]``, already baked into the poses) and ``applied_scale``; it is read with
:func:`gsw.data.loaders.load_instant_ngp`.

nerfstudio trains in a normalised frame: its dataparser re-orients and centres the poses (``T``, a rigid
``[3, 4]``) and scales their translations by ``s``; a splatfacto model (and the PLY ``ns-export
gaussian-splat`` writes) lives in that frame. The training run records ``T`` and ``s`` in
``dataparser_transforms.json`` (``{"transform": [3, 4], "scale": s}``), composed with the dataset's
``applied_transform`` ``A`` and ``applied_scale`` ``a`` when those exist (``T = T_orient @ A``, ``s = s_pose *
a``). This module moves the **cameras** into the model's frame: a camera-to-world pose ``[R | c]`` read from
``transforms.json`` becomes ``[T_orient R | s_pose (T_orient c)]`` with ``T_orient = T @ A^-1`` and ``s_pose =
s / a``. The model is left unchanged (rotating its SH coefficients would be lossy), so renders of the exported
PLY from the returned cameras match what nerfstudio rendered.

Example:
    >>> from gsw.data.nerfstudio import load_nerfstudio
    >>> run = "outputs/garden/splatfacto/run"
    >>> ds = load_nerfstudio("data/garden", dataparser_transforms=f"{run}/dataparser_transforms.json")  # doctest: +SKIP
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.data.loaders import Background, Dataset, DatasetError, _read_json, load_instant_ngp

__all__ = ["load_nerfstudio", "read_dataparser_transforms", "normalise_cameras", "is_nerfstudio_transforms",
           "PERSPECTIVE_MODELS"]

PERSPECTIVE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
"""nerfstudio ``camera_model`` values of perspective (radial-tangential) cameras, the ones supported."""


def is_nerfstudio_transforms(path: str | os.PathLike) -> bool:
    """Whether a ``transforms.json`` was written by nerfstudio (it has a top-level ``camera_model``)."""
    try:
        meta = _read_json(Path(path))
    except DatasetError:
        return False
    return isinstance(meta, dict) and "camera_model" in meta


def _matrix(value: Any, source: str, key: str) -> Tensor:
    try:
        m = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{source}: {key!r} must be a 3x4 or 4x4 matrix") from None
    if m.shape == (3, 4):
        m = torch.cat([m, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
    if m.shape != (4, 4) or not torch.isfinite(m).all():
        raise DatasetError(f"{source}: {key!r} must be a finite 3x4 or 4x4 matrix, got shape {list(m.shape)}")
    r = m[:3, :3]
    if float((r @ r.T - torch.eye(3, dtype=torch.float64)).abs().max()) > 1e-4 or float(torch.linalg.det(r)) < 0:
        raise DatasetError(f"{source}: the rotation of {key!r} is not orthonormal and right-handed")
    return m


def _positive(value: Any, source: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < float("inf"):
        raise DatasetError(f"{source}: {key!r} must be a positive number, got {value!r}")
    return float(value)


def read_dataparser_transforms(path: str | os.PathLike) -> tuple[Tensor, float]:
    """Read nerfstudio's ``dataparser_transforms.json``.

    Returns:
        ``(transform [4, 4] float64, scale)``.

    Raises:
        DatasetError: missing file, malformed JSON, a non-rigid transform or a non-positive scale.
    """
    path = Path(path)
    meta = _read_json(path)
    if not isinstance(meta, dict) or "transform" not in meta or "scale" not in meta:
        raise DatasetError(f"{path}: expected a JSON object with 'transform' and 'scale'")
    return _matrix(meta["transform"], str(path), "transform"), _positive(meta["scale"], str(path), "scale")


def normalise_cameras(cameras: Sequence[Camera], transform: Tensor, scale: float) -> list[Camera]:
    """Cameras moved by the similarity ``x -> scale * (transform @ [x; 1])`` (rigid ``transform [4, 4]``).

    A camera-to-world ``[R | c]`` becomes ``[A R | scale (A c + b)]`` (``A, b`` the rotation and translation of
    ``transform``); intrinsics, sizes and names are kept, so pixels project identically.
    """
    t = torch.as_tensor(transform, dtype=torch.float64)
    a, b = t[:3, :3], t[:3, 3]
    out = []
    for cam in cameras:
        v = cam.viewmat.detach().double().cpu()
        rotation = v[:3, :3] @ a.T
        viewmat = torch.eye(4, dtype=torch.float64)
        viewmat[:3, :3] = rotation
        viewmat[:3, 3] = scale * (v[:3, 3] - rotation @ b)
        out.append(replace(cam, viewmat=viewmat.to(cam.viewmat.dtype)))
    return out


def _pose_transform(meta: dict, transform: Tensor, scale: float, source: str) -> tuple[Tensor, float]:
    """The dataparser transform of the poses in ``transforms.json`` (without ``applied_transform/scale``)."""
    if "applied_transform" in meta:
        transform = transform @ torch.linalg.inv(_matrix(meta["applied_transform"], source, "applied_transform"))
    if "applied_scale" in meta:
        scale = scale / _positive(meta["applied_scale"], source, "applied_scale")
    return transform, scale


def load_nerfstudio(path: str | os.PathLike, split: str = "all", *,
                    dataparser_transforms: str | os.PathLike | None = None, downscale: float = 1,
                    background: Background = (1.0, 1.0, 1.0), undistort: bool = True,
                    holdout_every: int = 8) -> Dataset:
    """Load a nerfstudio dataset, optionally with cameras in a trained model's normalised frame.

    Args:
        path: ``transforms.json`` or its folder.
        split: ``"all"``, or ``"train"`` / ``"test"`` (``"val"`` = test) holding out every ``holdout_every``-th
            frame.
        dataparser_transforms: the training run's ``dataparser_transforms.json``; default: the one in the dataset
            folder if present, else none (cameras stay in the dataset's frame).
        downscale: image size divisor (>= 1).
        background: RGB for images with alpha.
        undistort: resample OpenCV-distorted images into pinhole cameras (else raise).
        holdout_every: hold-out period of ``split``.

    Returns:
        The :class:`~gsw.data.loaders.Dataset` (``format = "nerfstudio"``; ``meta["frame"]`` is
        ``"normalised"`` or ``"dataset"``, with ``meta["dataparser_transforms"]`` naming the file used).

    Raises:
        DatasetError: a non-perspective ``camera_model`` (fisheye, equirectangular), malformed files, missing
            images.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    meta = _read_json(path)
    if not isinstance(meta, dict):
        raise DatasetError(f"{path}: expected a JSON object")
    models = {meta.get("camera_model", "OPENCV")} | {f.get("camera_model") for f in meta.get("frames", [])
                                                     if isinstance(f, dict) and "camera_model" in f}
    unsupported = sorted(str(m) for m in models if m not in PERSPECTIVE_MODELS)
    if unsupported:
        raise DatasetError(f"{path}: camera_model {', '.join(unsupported)} is not supported "
                           f"(supported: {', '.join(PERSPECTIVE_MODELS)})")
    ds = load_instant_ngp(path, "test" if split == "val" else split, downscale=downscale, background=background,
                          undistort=undistort, holdout_every=holdout_every)
    if dataparser_transforms is None and (path.parent / "dataparser_transforms.json").is_file():
        dataparser_transforms = path.parent / "dataparser_transforms.json"
    info: dict[str, Any] = {"frame": "dataset"}
    cameras = ds.cameras
    if dataparser_transforms is not None:
        transform, scale = read_dataparser_transforms(dataparser_transforms)
        transform, scale = _pose_transform(meta, transform, scale, str(path))
        cameras = normalise_cameras(cameras, transform, scale)
        info = {"frame": "normalised", "dataparser_transforms": str(dataparser_transforms),
                "pose_transform": transform.tolist(), "pose_scale": scale}
    return replace(ds, cameras=cameras, format="nerfstudio", meta={**ds.meta, **info})
