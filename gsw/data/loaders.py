"""Dataset loaders: NeRF-synthetic, instant-ngp and INRIA 3DGS model folders.

Every loader returns cameras in the :mod:`gsw.camera` convention (world-to-camera, OpenCV axes, pixel ``(i, j)``
centred at ``(i + 0.5, j + 0.5)``) and images as ``[V, 3, H, W]`` float32 in ``[0, 1]``, composited on the
dataset background when the files have an alpha channel.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import torch
from torch import Tensor

from gsw.camera import Camera, save_inria_cameras
from gsw.data.distortion import Distortion, undistort_image
from gsw.data.images import IMAGE_SUFFIXES, composite, read_image, resize_image
from gsw.gaussians import Gaussians

__all__ = [
    "Dataset", "DatasetError", "InriaModel", "load_nerf_synthetic", "load_instant_ngp", "load_inria_model",
    "load_dataset", "detect_format", "save_inria_model",
    "scene_extent",
]

Background = Sequence[float] | Tensor


class DatasetError(ValueError):
    """A dataset is missing files, malformed, inconsistent or of an unknown format."""


@dataclass
class Dataset:
    """Posed images.

    Attributes:
        cameras: ``V`` cameras.
        images: ``[V, 3, H, W]`` float32 in ``[0, 1]`` (composited on :attr:`background` where the files had
            alpha).
        alphas: ``[V, 1, H, W]`` alpha masks, or ``None`` when the images had no alpha channel.
        names: ``V`` image names (relative file paths without extension for NeRF-style datasets).
        background: ``[3]`` RGB background the images were composited on.
        format: ``"nerf_synthetic"``, ``"instant_ngp"`` or ``"inria"``.
        points: optional ``[P, 3]`` point cloud for initialisation.
        point_colors: optional ``[P, 3]`` RGB in ``[0, 1]`` of :attr:`points`.
        meta: format-specific extras (e.g. instant-ngp ``aabb_scale``).
    """

    cameras: list[Camera]
    images: Tensor
    alphas: Tensor | None
    names: list[str]
    background: Tensor
    format: str = ""
    points: Tensor | None = None
    point_colors: Tensor | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        v = len(self.cameras)
        if self.images.dim() != 4 or self.images.shape[0] != v or self.images.shape[1] != 3:
            raise DatasetError(f"images must be [V={v}, 3, H, W], got {list(self.images.shape)}")
        if len(self.names) != v:
            raise DatasetError(f"{len(self.names)} names for {v} cameras")
        h, w = self.images.shape[-2:]
        for cam in self.cameras:
            if (cam.height, cam.width) != (h, w):
                raise DatasetError(f"camera {cam.name!r} is {cam.width}x{cam.height} but images are {w}x{h}")
        if self.alphas is not None and tuple(self.alphas.shape) != (v, 1, h, w):
            raise DatasetError(f"alphas must be [V, 1, H, W] = {[v, 1, h, w]}, got {list(self.alphas.shape)}")

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def height(self) -> int:
        """Image height ``H``."""
        return int(self.images.shape[-2])

    @property
    def width(self) -> int:
        """Image width ``W``."""
        return int(self.images.shape[-1])

    def subset(self, indices: Sequence[int]) -> "Dataset":
        """The views at ``indices`` (a new :class:`Dataset` sharing the point cloud)."""
        idx = list(indices)
        return Dataset(
            cameras=[self.cameras[i] for i in idx], images=self.images[idx],
            alphas=None if self.alphas is None else self.alphas[idx], names=[self.names[i] for i in idx],
            background=self.background, format=self.format, points=self.points, point_colors=self.point_colors,
            meta=dict(self.meta))


class InriaModel(NamedTuple):
    """What :func:`load_inria_model` returns (unpacks as ``gaussians, cameras, images``)."""

    gaussians: Gaussians
    cameras: list[Camera]
    images: Tensor | None
    iteration: int
    folder: Path


# ------------------------------------------------------------------------------------------- helpers


def _background(background: Background) -> Tensor:
    bg = torch.as_tensor(background, dtype=torch.float32).detach().cpu().flatten()
    if bg.shape != (3,) or not torch.isfinite(bg).all():
        raise ValueError(f"background must be 3 finite numbers, got {background!r}")
    return bg


def _check_downscale(downscale: float) -> float:
    if isinstance(downscale, bool) or not isinstance(downscale, (int, float)) or not downscale >= 1 \
            or not math.isfinite(downscale):
        raise ValueError(f"downscale must be a number >= 1, got {downscale!r}")
    return float(downscale)


def _read_json(path: Path) -> Any:
    if not path.is_file():
        raise DatasetError(f"missing file: {path}")
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as exc:
        raise DatasetError(f"malformed JSON in {path}: {exc}") from None


def _resolve_image(root: Path, file_path: str, context: str) -> Path:
    p = Path(file_path)
    path = p if p.is_absolute() else root / p
    if path.suffix in IMAGE_SUFFIXES and path.is_file():
        return path
    if path.suffix not in IMAGE_SUFFIXES or not path.is_file():
        for suffix in (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG"):
            candidate = path.with_name(path.name + suffix)
            if candidate.is_file():
                return candidate
    if path.is_file():
        return path
    raise DatasetError(f"{context}: image not found: {path} (also tried .png/.jpg/.jpeg)")


def _number(obj: dict, key: str, context: str, default: Any = None) -> Any:
    value = obj.get(key, default)
    if value is default:
        return default
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DatasetError(f"{context}: {key!r} must be a finite number, got {value!r}")
    return float(value)


def _c2w(frame: dict, context: str) -> Tensor:
    if "transform_matrix" not in frame:
        raise DatasetError(f"{context}: frame lacks 'transform_matrix'")
    try:
        m = torch.tensor(frame["transform_matrix"], dtype=torch.float64)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{context}: malformed transform_matrix ({exc})") from None
    if m.shape == (3, 4):
        m = torch.cat([m, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
    if m.shape != (4, 4) or not torch.isfinite(m).all():
        raise DatasetError(f"{context}: transform_matrix must be a finite 4x4 (or 3x4) matrix")
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


def _load_frames(root: Path, meta: dict, frames: list[dict], *, source: str, downscale: float,
                 background: Tensor, undistort: bool, fmt: str) -> Dataset:
    """Shared NeRF / instant-ngp frame parser (intrinsics per frame or at the top level)."""
    cameras, images, alphas, names = [], [], [], []
    any_alpha = False
    size: tuple[int, int] | None = None
    for k, frame in enumerate(frames):
        ctx = f"{source} frame {k}"
        if not isinstance(frame, dict) or "file_path" not in frame:
            raise DatasetError(f"{ctx}: frame lacks 'file_path'")
        path = _resolve_image(root, str(frame["file_path"]), ctx)
        try:
            img = read_image(path)
        except ValueError as exc:
            raise DatasetError(f"{ctx}: {exc}") from None
        h, w = img.shape[-2:]
        get = lambda key: _number(frame, key, ctx, _number(meta, key, source))  # noqa: E731
        fw, fh = get("w"), get("h")
        if (fw is not None and int(fw) != w) or (fh is not None and int(fh) != h):
            raise DatasetError(f"{ctx}: {path.name} is {w}x{h} but the transforms file says "
                               f"{int(fw or w)}x{int(fh or h)}")
        if size is None:
            size = (h, w)
        elif size != (h, w):
            raise DatasetError(f"inconsistent image sizes in {source}: {path.name} is {w}x{h}, "
                               f"earlier images are {size[1]}x{size[0]}")
        fl_x, fl_y = get("fl_x"), get("fl_y")
        angle_x, angle_y = get("camera_angle_x"), get("camera_angle_y")
        if fl_x is None and angle_x is None:
            raise DatasetError(f"{ctx}: no focal length (need 'fl_x' or 'camera_angle_x')")
        if fl_x is None:
            fl_x = w / (2.0 * math.tan(angle_x / 2.0))
        if fl_y is None:
            fl_y = h / (2.0 * math.tan(angle_y / 2.0)) if angle_y is not None else fl_x
        cx, cy = get("cx"), get("cy")
        cx = w / 2.0 if cx is None else cx
        cy = h / 2.0 if cy is None else cy
        if frame.get("is_fisheye", meta.get("is_fisheye", False)):
            raise DatasetError(f"{ctx}: fisheye cameras (is_fisheye) are not supported")
        dist = Distortion(*(get(key) or 0.0 for key in ("k1", "k2", "p1", "p2", "k3")))
        if (get("k4") or 0.0) != 0.0:
            raise DatasetError(f"{ctx}: k4 (fisheye model) is not supported")
        c2w = _c2w(frame, ctx)
        if not dist.is_identity:
            if not undistort:
                raise DatasetError(
                    f"{ctx}: the camera has lens distortion (k1={dist.k1}, k2={dist.k2}, p1={dist.p1}, "
                    f"p2={dist.p2}, k3={dist.k3}) and undistort=False; pass undistort=True to resample the "
                    "images into pinhole cameras")
            img = undistort_image(img, fl_x, fl_y, cx, cy, dist)
        if img.shape[0] == 4:
            any_alpha = True
            rgb, alpha = composite(img, background)
        else:
            rgb, alpha = img, torch.ones_like(img[:1])
        name = str(frame["file_path"])
        cam = Camera.from_nerf(c2w, w, h, fx=fl_x, fy=fl_y, cx=cx, cy=cy, name=name)
        if downscale != 1.0:
            cam = cam.scaled(1.0 / downscale)
            rgb = resize_image(rgb, cam.height, cam.width)
            alpha = resize_image(alpha, cam.height, cam.width)
        cameras.append(cam)
        images.append(rgb)
        alphas.append(alpha)
        names.append(name)
    if not cameras:
        raise DatasetError(f"{source}: no frames")
    return Dataset(cameras=cameras, images=torch.stack(images).contiguous(),
                   alphas=torch.stack(alphas).contiguous() if any_alpha else None, names=names,
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
    if not path.is_file():
        train_path = root / "transforms_train.json"
        if not train_path.is_file():
            raise DatasetError(f"missing file: {path} (and no transforms_train.json in {root})")
        if split != "train" and holdout_every < 2:
            raise DatasetError(f"missing file: {path} and holdout_every={holdout_every} disables the hold-out split")
        path, derived = train_path, True
    elif split == "train" and holdout_every >= 2 and not any(
            (root / f"transforms_{s}.json").is_file() for s in ("test", "val")):
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


# ------------------------------------------------------------------------------------------- INRIA


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
                     background: Background = (1.0, 1.0, 1.0)) -> InriaModel:
    """Load an INRIA 3DGS output folder: ``point_cloud/iteration_*/point_cloud.ply`` + ``cameras.json``.

    Args:
        folder: the model folder.
        iteration: which ``iteration_N`` to load (default: the largest).
        images_dir: optional folder with the source images, matched by ``img_name`` (with or without an
            extension); images are resized to each camera's size when they differ by a consistent factor
            (INRIA stores the training resolution in ``cameras.json``).
        downscale: extra size divisor applied to cameras and images (>= 1).
        background: RGB for RGBA source images.

    Returns:
        :class:`InriaModel` ``(gaussians, cameras, images or None, iteration, folder)``.
    """
    from gsw.io.ply import load_ply  # noqa: PLC0415

    folder = Path(folder)
    downscale = _check_downscale(downscale)
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
    gaussians = load_ply(ply)
    entries = _read_json(folder / "cameras.json")
    if not isinstance(entries, list) or not entries:
        raise DatasetError(f"{folder / 'cameras.json'}: expected a non-empty JSON list of camera entries")
    cameras = []
    for k, e in enumerate(entries):
        try:
            cameras.append(Camera.from_inria(e))
        except (ValueError, TypeError) as exc:
            raise DatasetError(f"{folder / 'cameras.json'} entry {k}: {exc}") from None
    if downscale != 1.0:
        cameras = [c.scaled(1.0 / downscale) for c in cameras]
    images = None
    if images_dir is not None:
        images = _load_named_images(Path(images_dir), cameras, _background(background))
    return InriaModel(gaussians, cameras, images, iteration, folder)


def _load_named_images(images_dir: Path, cameras: Sequence[Camera], bg: Tensor) -> Tensor:
    if not images_dir.is_dir():
        raise DatasetError(f"images folder not found: {images_dir}")
    out = []
    for cam in cameras:
        if not cam.name:
            raise DatasetError("camera entry has no img_name; cannot match it to an image file")
        path = _resolve_image(images_dir, cam.name, f"camera {cam.name!r}")
        img = read_image(path)
        rgb = composite(img, bg)[0] if img.shape[0] == 4 else img
        h, w = rgb.shape[-2:]
        if (h, w) != (cam.height, cam.width):
            fx, fy = w / cam.width, h / cam.height
            if abs(fx - fy) > 0.02 * max(fx, fy):
                raise DatasetError(f"{path.name} is {w}x{h}, which is not a uniform rescale of the camera's "
                                   f"{cam.width}x{cam.height}")
            rgb = resize_image(rgb, cam.height, cam.width)
        out.append(rgb)
    return torch.stack(out).contiguous()


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
    if any((path / f"transforms_{s}.json").is_file() for s in ("train", "val", "test")):
        return "nerf_synthetic"
    if (path / "transforms.json").is_file():
        return "instant_ngp"
    if (path / "cameras.json").is_file() or (path / "point_cloud").is_dir():
        return "inria"
    raise DatasetError(f"unknown dataset format in {path}: expected {SUPPORTED_DATASETS}")


def load_dataset(path: str | os.PathLike, split: str = "train", *, downscale: float = 1,
                 background: Background = (1.0, 1.0, 1.0), holdout_every: int = 8, undistort: bool = True,
                 images_dir: str | os.PathLike | None = None) -> Dataset:
    """Load any supported dataset, detecting the format (see :func:`detect_format`).

    ``split`` is ``"train"`` / ``"test"`` / ``"val"`` (NeRF rules, see :func:`load_nerf_synthetic`); for
    instant-ngp and INRIA folders without a split, ``train``/``test`` hold out every ``holdout_every``-th view
    (``"all"`` keeps every view). An INRIA folder needs ``images_dir``; its Gaussians become the point cloud
    (``points``/``point_colors``).
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
    model = load_inria_model(path, images_dir=images_dir, downscale=downscale, background=background)
    idx = list(range(len(model.cameras)))
    if split != "all":
        train_idx, test_idx = holdout_indices(len(idx), holdout_every)
        idx = train_idx if split == "train" else test_idx
    from gsw.constants import SH_C0, SH_COLOR_OFFSET  # noqa: PLC0415

    g = model.gaussians
    assert model.images is not None
    return Dataset(cameras=[model.cameras[i] for i in idx], images=model.images[idx], alphas=None,
                   names=[model.cameras[i].name for i in idx], background=_background(background), format="inria",
                   points=g.means.detach().float(),
                   point_colors=(g.sh[:, 0].detach().float() * SH_C0 + SH_COLOR_OFFSET).clamp(0, 1),
                   meta={"iteration": model.iteration})


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
