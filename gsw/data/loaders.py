"""Dataset loaders: NeRF-synthetic, instant-ngp and INRIA 3DGS model folders.

Every loader returns cameras in the :mod:`gsw.camera` convention (world-to-camera, OpenCV axes, pixel ``(i, j)``
centred at ``(i + 0.5, j + 0.5)``) and images as ``[V, 3, H, W]`` float32 in ``[0, 1]``, composited on the
dataset background when the files have an alpha channel.

Inputs are checked, never silently adapted: JSON fields are type-checked (:mod:`gsw.camera_io`), every
missing image is named in one error, an image whose size differs from its camera's is an error (images
are resized only by an explicit ``downscale``, or ``resize_images=True`` for INRIA folders), and views
smaller than :data:`MIN_IMAGE_SIZE` pixels on a side are rejected.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.camera_io import json_integer, json_matrix
from gsw.data.dataset import MIN_IMAGE_SIZE, Background, Dataset, DatasetError, _background, _check_downscale, \
    _check_usable, _find_images, _number, _read_json, _read_view
from gsw.data.distortion import Distortion, undistort_image
from gsw.data.images import composite, resize_image
from gsw.data.inria import InriaModel, load_inria_model, save_inria_model
from gsw.gaussians import sh_dc_to_rgb

__all__ = [
    "Dataset", "DatasetError", "InriaModel", "load_nerf_synthetic", "load_instant_ngp", "load_inria_model",
    "load_dataset", "detect_format", "save_inria_model", "scene_extent", "MIN_IMAGE_SIZE",
]


def _c2w(frame: dict, context: str) -> Tensor:
    if "transform_matrix" not in frame:
        raise DatasetError(f"{context}: frame lacks 'transform_matrix'")
    value = frame["transform_matrix"]
    rows = 3 if isinstance(value, list) and len(value) == 3 else 4  # 3x4 is accepted too
    m = json_matrix(value, (rows, 4), "transform_matrix", context, error=DatasetError)
    if rows == 3:
        m = torch.cat([m, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
    # Orthonormalise the rotation (some exporters round it) so Camera accepts it.
    u, _, vh = torch.linalg.svd(m[:3, :3])
    r = u @ vh
    if float(torch.linalg.det(r)) < 0:
        raise DatasetError(f"{context}: transform_matrix rotation is a reflection")
    if float((r - m[:3, :3]).abs().max()) > 1e-2:
        raise DatasetError(f"{context}: transform_matrix rotation is not orthonormal (scaled poses are unsupported)")
    m = m.clone()
    m[:3, :3] = r
    return m


def _intrinsics(get: Any, ctx: str, w: int, h: int) -> tuple[float, float, float, float]:
    """``fx, fy, cx, cy`` of a NeRF / instant-ngp frame (``get`` reads a checked number, frame then top level)."""
    fl_x, fl_y = get("fl_x", positive=True), get("fl_y", positive=True)
    angle_x, angle_y = get("camera_angle_x"), get("camera_angle_y")
    for name, angle in (("camera_angle_x", angle_x), ("camera_angle_y", angle_y)):
        if angle is not None and not 0.0 < angle < math.pi:
            raise DatasetError(f"{ctx}: field {name!r} must be in (0, pi) radians, got {angle!r}")
    if fl_x is None and angle_x is None:
        raise DatasetError(f"{ctx}: no focal length (need 'fl_x' or 'camera_angle_x')")
    if fl_x is None:
        fl_x = w / (2.0 * math.tan(angle_x / 2.0))
    if fl_y is None:
        fl_y = h / (2.0 * math.tan(angle_y / 2.0)) if angle_y is not None else fl_x
    cx, cy = get("cx"), get("cy")
    return fl_x, fl_y, w / 2.0 if cx is None else cx, h / 2.0 if cy is None else cy


def _distortion(get: Any, frame: dict, meta: dict, ctx: str) -> Distortion:
    if frame.get("is_fisheye", meta.get("is_fisheye", False)):
        raise DatasetError(f"{ctx}: fisheye cameras (is_fisheye) are not supported")
    if (get("k4") or 0.0) != 0.0:
        raise DatasetError(f"{ctx}: k4 (fisheye model) is not supported")
    return Distortion(*(get(key) or 0.0 for key in ("k1", "k2", "p1", "p2", "k3")))


def _load_frame(path: Path, frame: dict, meta: dict, ctx: str, *, downscale: float, background: Tensor,
                undistort: bool) -> tuple[Camera, Tensor, Tensor | None, tuple[int, int]]:
    """One view: ``(camera, rgb [3, H, W], alpha [1, H, W] or None, (H, W) of the file)``."""
    img = _read_view(path, ctx)
    h, w = img.shape[-2:]

    def get(key: str, positive: bool = False) -> Any:
        return _number(frame, key, ctx, _number(meta, key, ctx, positive=positive), positive=positive)

    fw = json_integer(frame, "w", ctx, json_integer(meta, "w", ctx, None, error=DatasetError), error=DatasetError)
    fh = json_integer(frame, "h", ctx, json_integer(meta, "h", ctx, None, error=DatasetError), error=DatasetError)
    if (fw is not None and fw != w) or (fh is not None and fh != h):
        raise DatasetError(f"{ctx}: {path.name} is {w}x{h} but the transforms file says {fw or w}x{fh or h}")
    fl_x, fl_y, cx, cy = _intrinsics(get, ctx, w, h)
    dist = _distortion(get, frame, meta, ctx)
    c2w = _c2w(frame, ctx)
    if not dist.is_identity:
        if not undistort:
            raise DatasetError(
                f"{ctx}: the camera has lens distortion (k1={dist.k1}, k2={dist.k2}, p1={dist.p1}, "
                f"p2={dist.p2}, k3={dist.k3}) and undistort=False; pass undistort=True to resample the "
                "images into pinhole cameras")
        img = undistort_image(img, fl_x, fl_y, cx, cy, dist)
    rgb, alpha = composite(img, background) if img.shape[0] == 4 else (img, None)
    try:
        cam = Camera.from_nerf(c2w, w, h, fx=fl_x, fy=fl_y, cx=cx, cy=cy, name=str(frame["file_path"]))
    except ValueError as exc:
        raise DatasetError(f"{ctx}: {exc}") from None
    if downscale != 1.0:  # the explicit, documented resize
        cam = cam.scaled(1.0 / downscale)
        rgb = resize_image(rgb, cam.height, cam.width)
        alpha = None if alpha is None else resize_image(alpha, cam.height, cam.width)
    _check_usable(cam.width, cam.height, f"{ctx}: {path.name}")
    return cam, rgb, alpha, (h, w)


def _load_frames(root: Path, meta: dict, frames: list, *, source: str, downscale: float,
                 background: Tensor, undistort: bool, fmt: str) -> Dataset:
    """Shared NeRF / instant-ngp frame parser (intrinsics per frame or at the top level)."""
    if not frames:
        raise DatasetError(f"{source}: no frames")
    for k, frame in enumerate(frames):
        if not isinstance(frame, dict) or "file_path" not in frame:
            raise DatasetError(f"{source} frame {k}: frame lacks 'file_path'")
        if not isinstance(frame["file_path"], str) or not frame["file_path"]:
            raise DatasetError(f"{source} frame {k}: field 'file_path' must be a non-empty string, "
                               f"got {frame['file_path']!r}")
    paths = _find_images(root, [f["file_path"] for f in frames], source)
    cameras, images, alphas, sizes = [], [], [], []
    for k, (frame, path) in enumerate(zip(frames, paths)):
        cam, rgb, alpha, (h, w) = _load_frame(path, frame, meta, f"{source} frame {k}", downscale=downscale,
                                              background=background, undistort=undistort)
        if sizes and (h, w) != sizes[0]:
            raise DatasetError(f"inconsistent image sizes in {source}: {path.name} is {w}x{h}, "
                               f"earlier images are {sizes[0][1]}x{sizes[0][0]}")
        sizes.append((h, w))
        cameras.append(cam)
        images.append(rgb)
        alphas.append(alpha)
    any_alpha = any(a is not None for a in alphas)
    alpha_stack = torch.stack([torch.ones_like(rgb[:1]) if a is None else a for a, rgb in zip(alphas, images)])
    return Dataset(cameras=cameras, images=torch.stack(images).contiguous(),
                   alphas=alpha_stack.contiguous() if any_alpha else None, names=[c.name for c in cameras],
                   background=background, format=fmt)


def _frames_of(meta: Any, source: str) -> list:
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise DatasetError(f"{source}: expected a JSON object with a 'frames' list")
    return meta["frames"]


# ------------------------------------------------------------------------------------------- loaders


def holdout_indices(n: int, every: int) -> tuple[list[int], list[int]]:
    """Train / test split holding out every ``every``-th view (indices ``0, every, 2 every, ...`` are test)."""
    if every < 2:
        raise ValueError(f"holdout_every must be >= 2, got {every}")
    test = list(range(0, n, every))
    return [i for i in range(n) if i % every], test


def load_nerf_synthetic(root: str | os.PathLike, split: str = "train", *, downscale: float = 1,
                        background: Background = (1.0, 1.0, 1.0), holdout_every: int = 8) -> Dataset:
    """Load a NeRF-synthetic (Blender) scene: ``transforms_{train,val,test}.json`` + RGBA images.

    Cameras come from ``camera_angle_x`` (horizontal FoV) and the camera-to-world ``transform_matrix`` in the
    OpenGL convention (converted to OpenCV). Images are composited on ``background``.

    Split rule: when ``transforms_{split}.json`` exists it is used as is. When the folder has only
    ``transforms_train.json`` (like ``../shared/data/lego``), every ``holdout_every``-th train view
    (indices 0, 8, 16, ...) is the ``test`` (and ``val``) split and ``train`` is the remaining views.
    ``holdout_every=0`` disables this (``train`` is then every view, ``test`` is an error).

    Args:
        root: the scene folder.
        split: ``"train"``, ``"val"`` or ``"test"``.
        downscale: image size divisor (>= 1; 4 turns 800x800 into 200x200, box-filtered).
        background: RGB the RGBA images are composited on (``(1, 1, 1)`` white, ``(0, 0, 0)`` black).
        holdout_every: hold-out period when the scene has no file for ``split``.

    Returns:
        The :class:`Dataset` (``format = "nerf_synthetic"``; ``meta["holdout"]`` tells whether the split was
        derived by hold-out).

    Raises:
        DatasetError: missing folder/files, malformed JSON, inconsistent image sizes.
    """
    root = Path(root)
    if split not in ("train", "val", "test"):
        raise ValueError(f"split must be 'train', 'val' or 'test', got {split!r}")
    downscale = _check_downscale(downscale)
    bg = _background(background)
    if not root.is_dir():
        raise DatasetError(f"dataset folder not found: {root}")
    path = root / f"transforms_{split}.json"
    derived = False
    if not path.exists():
        train_path = root / "transforms_train.json"
        if not train_path.exists():
            raise DatasetError(f"missing file: {path} (and no transforms_train.json in {root})")
        if split != "train" and holdout_every < 2:
            raise DatasetError(f"missing file: {path} and holdout_every={holdout_every} disables the hold-out split")
        path, derived = train_path, True
    elif split == "train" and holdout_every >= 2 and not any(
            (root / f"transforms_{s}.json").exists() for s in ("test", "val")):
        derived = True
    meta = _read_json(path)
    frames = _frames_of(meta, str(path))
    if derived and holdout_every >= 2:
        train_idx, test_idx = holdout_indices(len(frames), holdout_every)
        frames = [frames[i] for i in (train_idx if split == "train" else test_idx)]
    ds = _load_frames(root, meta, frames, source=str(path), downscale=downscale, background=bg, undistort=False,
                      fmt="nerf_synthetic")
    ds.meta.update(split=split, holdout=derived, holdout_every=holdout_every if derived else None,
                   transforms=str(path))
    return ds


def load_instant_ngp(path: str | os.PathLike, split: str = "all", *, downscale: float = 1,
                     background: Background = (1.0, 1.0, 1.0), undistort: bool = True,
                     holdout_every: int = 8) -> Dataset:
    """Load an instant-ngp capture: ``transforms.json`` with ``fl_x, fl_y, cx, cy, w, h`` (top level or per
    frame), optional ``k1, k2, p1, p2`` (and ``k3``) OpenCV distortion and ``aabb_scale``.

    Poses are used as stored (instant-ngp's own ``scale``/``offset`` normalisation is applied by instant-ngp at
    load time and is not part of the camera model; they are kept in ``meta``). ``cx, cy`` are read in the
    image-edge convention (COLMAP's, which ``colmap2nerf.py`` copies). Distorted captures are resampled into
    pinhole cameras with the same intrinsics (``undistort=True``) or rejected (``undistort=False``).

    Args:
        path: the ``transforms.json`` file or its folder.
        split: ``"all"`` (every frame), or ``"train"`` / ``"test"`` for the every-``holdout_every``-th hold-out.
        downscale: image size divisor (>= 1).
        background: RGB for RGBA images.
        undistort: resample distorted images (else raise on non-zero distortion).
        holdout_every: hold-out period for ``split`` = train/test.

    Returns:
        The :class:`Dataset` (``format = "instant_ngp"``, ``meta`` has ``aabb_scale``, ``scale``, ``offset``).
    """
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    if split not in ("all", "train", "test", "val"):
        raise ValueError(f"split must be 'all', 'train', 'test' or 'val', got {split!r}")
    downscale = _check_downscale(downscale)
    bg = _background(background)
    meta = _read_json(path)
    frames = _frames_of(meta, str(path))
    if split != "all":
        train_idx, test_idx = holdout_indices(len(frames), holdout_every)
        frames = [frames[i] for i in (train_idx if split == "train" else test_idx)]
    ds = _load_frames(path.parent, meta, frames, source=str(path), downscale=downscale, background=bg,
                      undistort=undistort, fmt="instant_ngp")
    ds.meta.update({k: meta[k] for k in ("aabb_scale", "scale", "offset") if k in meta})
    ds.meta.update(split=split, transforms=str(path))
    return ds


# ------------------------------------------------------------------------------------------- auto-detect


def detect_format(path: str | os.PathLike) -> str:
    """``"nerf_synthetic"``, ``"instant_ngp"``, ``"inria"``, or ``"colmap"`` / ``"llff"`` / ``"nerfstudio"``
    (:mod:`gsw.data.formats`) for a dataset path (folder or transforms file).

    Raises:
        DatasetError: when nothing recognisable is there.
    """
    from gsw.data.formats import SUPPORTED_DATASETS, detect_extra_format  # noqa: PLC0415 - COLMAP, LLFF, nerfstudio

    path = Path(path)
    if not path.exists():
        raise DatasetError(f"dataset path not found: {path}")
    if (extra := detect_extra_format(path)) is not None:
        return extra
    if path.is_file():
        if path.name.startswith("transforms") and path.suffix == ".json":
            return "instant_ngp" if path.name == "transforms.json" else "nerf_synthetic"
        raise DatasetError(f"unknown dataset format: {path} (expected a folder or a transforms*.json file)")
    if any((path / f"transforms_{s}.json").exists() for s in ("train", "val", "test")):
        return "nerf_synthetic"
    if (path / "transforms.json").exists():
        return "instant_ngp"
    if (path / "cameras.json").exists() or (path / "point_cloud").is_dir():
        return "inria"
    raise DatasetError(f"unknown dataset format in {path}: expected {SUPPORTED_DATASETS}")


def load_dataset(path: str | os.PathLike, split: str = "train", *, downscale: float = 1,
                 background: Background = (1.0, 1.0, 1.0), holdout_every: int = 8, undistort: bool = True,
                 images_dir: str | os.PathLike | None = None, resize_images: bool = False) -> Dataset:
    """Load any supported dataset, detecting the format (see :func:`detect_format`).

    ``split`` is ``"train"`` / ``"test"`` / ``"val"`` (NeRF rules, see :func:`load_nerf_synthetic`); for
    instant-ngp and INRIA folders without a split, ``train``/``test`` hold out every ``holdout_every``-th view
    (``"all"`` keeps every view). An INRIA folder needs ``images_dir``; its Gaussians become the point cloud
    (``points``/``point_colors``); ``resize_images`` is its opt-in for photos at another size than
    ``cameras.json`` (:func:`load_inria_model`; ``meta["resized"]`` names them).
    """
    fmt = detect_format(path)
    from gsw.data.formats import EXTRA_FORMATS, load_extra_dataset  # noqa: PLC0415 - COLMAP, LLFF, nerfstudio

    if fmt in EXTRA_FORMATS:
        return load_extra_dataset(fmt, path, split, downscale=downscale, background=background,
                                  holdout_every=holdout_every, undistort=undistort, images_dir=images_dir)
    if fmt == "nerf_synthetic":
        p = Path(path)
        return load_nerf_synthetic(p.parent if p.is_file() else p, split, downscale=downscale,
                                   background=background, holdout_every=holdout_every)
    if fmt == "instant_ngp":
        return load_instant_ngp(path, "test" if split == "val" else split, downscale=downscale,
                                background=background, undistort=undistort, holdout_every=holdout_every)
    if images_dir is None:
        raise DatasetError(f"{path} is an INRIA model folder; pass images_dir to use it as a dataset")
    model = load_inria_model(path, images_dir=images_dir, downscale=downscale, background=background,
                             resize_images=resize_images)
    idx = list(range(len(model.cameras)))
    if split != "all":
        train_idx, test_idx = holdout_indices(len(idx), holdout_every)
        idx = train_idx if split == "train" else test_idx
    g = model.gaussians
    assert model.images is not None
    return Dataset(cameras=[model.cameras[i] for i in idx], images=model.images[idx], alphas=None,
                   names=[model.cameras[i].name for i in idx], background=_background(background), format="inria",
                   points=g.means.detach().float(),
                   point_colors=sh_dc_to_rgb(g.sh[:, 0].detach().float()).clamp(0, 1),
                   meta={"iteration": model.iteration, "resized": list(model.resized)})


# ------------------------------------------------------------------------------------------- geometry


def scene_extent(cameras: Sequence[Camera]) -> tuple[Tensor, float]:
    """INRIA's ``getNerfppNorm``: centre of the camera centres and ``1.1 x`` the largest distance from it.

    Returns:
        ``(center [3] float64, radius)``; radius is at least 1e-6... (1.0 for a single camera).
    """
    centers = torch.stack([c.center.detach().double().cpu() for c in cameras])
    center = centers.mean(0)
    radius = float((centers - center).norm(dim=1).max()) * 1.1
    return center, radius if radius > 0 else 1.0
