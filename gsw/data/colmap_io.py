"""COLMAP sparse models: ``cameras``, ``images`` and ``points3D`` as binary (``.bin``) or text (``.txt``) files.

Binary layout (little endian; COLMAP 3.x and 4.x write the same three files, 4.x adds ``rigs``/``frames``
which are not needed here)::

    cameras.bin   uint64 count, then per camera: int32 camera_id, int32 model_id, uint64 width,
                  uint64 height, float64 params[num_params(model)]
    images.bin    uint64 count, then per image: int32 image_id, float64 qw qx qy qz tx ty tz,
                  int32 camera_id, NUL-terminated name, uint64 num_points2D,
                  num_points2D x (float64 x, float64 y, int64 point3D_id)
    points3D.bin  uint64 count, then per point: uint64 point3D_id, float64 x y z, uint8 r g b,
                  float64 error, uint64 track_length, track_length x (int32 image_id, int32 point2D_idx)

The text files hold the same fields, one camera / point per line and two lines per image (the second lists
the 2-D points); ``#`` starts a comment. ``(qw, qx, qy, qz, tx, ty, tz)`` is the world-to-camera pose
(OpenCV axes), the :mod:`gsw.camera` convention. Only what datasets need is kept: 2-D observations and tracks
are parsed past, not stored.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Sequence

import numpy as np

from gsw._atomic import atomic_write

__all__ = ["ColmapCamera", "ColmapImage", "ColmapModel", "ColmapError", "CAMERA_MODELS", "read_colmap_model",
           "write_colmap_model", "find_colmap_model"]

#: COLMAP camera models: id -> (name, number of parameters).
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
_MODEL_IDS = {name: (model_id, count) for model_id, (name, count) in CAMERA_MODELS.items()}


class ColmapError(ValueError):
    """A COLMAP model is missing, malformed or inconsistent."""


@dataclass
class ColmapCamera:
    """One ``cameras`` entry: ``model`` name, size in pixels and the model's parameters."""

    camera_id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass
class ColmapImage:
    """One ``images`` entry: world-to-camera rotation ``qvec = (w, x, y, z)`` and translation ``tvec``."""

    image_id: int
    qvec: tuple[float, float, float, float]
    tvec: tuple[float, float, float]
    camera_id: int
    name: str


@dataclass
class ColmapModel:
    """A sparse model: cameras by id, images (in file order) and the 3-D points.

    Attributes:
        cameras: ``camera_id -> ColmapCamera``.
        images: the registered images.
        points: ``[P, 3]`` float64 positions.
        colors: ``[P, 3]`` uint8 RGB.
    """

    cameras: dict[int, ColmapCamera]
    images: list[ColmapImage]
    points: np.ndarray
    colors: np.ndarray


# ---------------------------------------------------------------------------------------------- binary


class _Reader:
    """Bounds-checked little-endian reads from a binary file."""

    def __init__(self, f: BinaryIO, path: Path):
        self.data = f.read()
        self.pos = 0
        self.path = path

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise ColmapError(f"{self.path}: truncated file while reading {what}")
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return out

    def skip(self, size: int, what: str) -> None:
        if size < 0 or self.pos + size > len(self.data):
            raise ColmapError(f"{self.path}: truncated file while reading {what}")
        self.pos += size

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise ColmapError(f"{self.path}: truncated file while reading {what} (no NUL terminator)")
        raw, self.pos = self.data[self.pos : end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise ColmapError(f"{self.path}: {what} is not UTF-8") from None

    def finish(self) -> None:
        if self.pos != len(self.data):
            raise ColmapError(f"{self.path}: {len(self.data) - self.pos} unexpected bytes at the end")


def _model_params(model_id: int, path: Path, camera_id: int) -> tuple[str, int]:
    if model_id not in CAMERA_MODELS:
        raise ColmapError(f"{path}: camera {camera_id} has unknown model id {model_id}")
    return CAMERA_MODELS[model_id]


def _read_cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    with open(path, "rb") as f:
        r = _Reader(f, path)
    cameras = {}
    for _ in range(r.take("Q", "the camera count")[0]):
        camera_id, model_id, width, height = r.take("iiQQ", "a camera")
        name, count = _model_params(model_id, path, camera_id)
        cameras[camera_id] = ColmapCamera(camera_id, name, width, height, r.take(f"{count}d", "camera params"))
    r.finish()
    return cameras


def _read_images_bin(path: Path) -> list[ColmapImage]:
    with open(path, "rb") as f:
        r = _Reader(f, path)
    images = []
    for _ in range(r.take("Q", "the image count")[0]):
        image_id, *pose, camera_id = r.take("i7di", "an image pose")
        name = r.name(f"the name of image {image_id}")
        r.skip(24 * r.take("Q", "a 2-D point count")[0], f"the 2-D points of image {image_id}")
        images.append(ColmapImage(image_id, tuple(pose[:4]), tuple(pose[4:]), camera_id, name))
    r.finish()
    return images


def _read_points_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with open(path, "rb") as f:
        r = _Reader(f, path)
    points, colors = [], []
    for _ in range(r.take("Q", "the point count")[0]):
        _, x, y, z, red, green, blue, _, track = r.take("Q3d3BdQ", "a 3-D point")
        r.skip(8 * track, "a point track")
        points.append((x, y, z))
        colors.append((red, green, blue))
    r.finish()
    return np.array(points, dtype=np.float64).reshape(-1, 3), np.array(colors, dtype=np.uint8).reshape(-1, 3)


# ---------------------------------------------------------------------------------------------- text


def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, words) of the non-comment lines; blank lines kept (they are empty 2-D point lists)."""
    out = []
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, 1):
            if not line.lstrip().startswith("#"):
                out.append((number, line.split()))
    while out and not out[-1][1]:
        out.pop()
    return out


def _parse(words: Sequence[str], types: Sequence[type], path: Path, number: int, what: str) -> list:
    if len(words) < len(types):
        raise ColmapError(f"{path}:{number}: {what} needs {len(types)} fields, found {len(words)}")
    try:
        return [t(w) for t, w in zip(types, words)]
    except ValueError as exc:
        raise ColmapError(f"{path}:{number}: malformed {what} ({exc})") from None


def _read_cameras_txt(path: Path) -> dict[int, ColmapCamera]:
    cameras = {}
    for number, words in _data_lines(path):
        if not words:
            continue
        camera_id, model, width, height = _parse(words, (int, str, int, int), path, number, "camera line")
        if model not in _MODEL_IDS:
            raise ColmapError(f"{path}:{number}: unknown camera model {model!r}")
        count = _MODEL_IDS[model][1]
        if len(words) != 4 + count:
            raise ColmapError(f"{path}:{number}: {model} has {count} parameters, found {len(words) - 4}")
        params = _parse(words[4:], [float] * count, path, number, "camera parameters")
        cameras[camera_id] = ColmapCamera(camera_id, model, width, height, tuple(params))
    return cameras


def _read_images_txt(path: Path) -> list[ColmapImage]:
    lines = [(n, w) for n, w in _data_lines(path)]
    images = []
    i = 0
    while i < len(lines):
        number, words = lines[i]
        if not words:  # tolerate stray blank lines between entries
            i += 1
            continue
        if len(words) < 10:
            raise ColmapError(f"{path}:{number}: an image line needs IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        values = _parse(words, (int,) + (float,) * 7 + (int,), path, number, "image line")
        name = " ".join(words[9:])
        images.append(ColmapImage(values[0], tuple(values[1:5]), tuple(values[5:8]), values[8], name))
        i += 2  # the next line lists the 2-D points (possibly empty)
    return images


def _read_points_txt(path: Path) -> tuple[np.ndarray, np.ndarray]:
    points, colors = [], []
    for number, words in _data_lines(path):
        if not words:
            continue
        values = _parse(words, (int, float, float, float, int, int, int), path, number, "point line")
        if any(not 0 <= c <= 255 for c in values[4:7]):
            raise ColmapError(f"{path}:{number}: point colour outside 0..255")
        points.append(values[1:4])
        colors.append(values[4:7])
    return np.array(points, dtype=np.float64).reshape(-1, 3), np.array(colors, dtype=np.uint8).reshape(-1, 3)


# ---------------------------------------------------------------------------------------------- API


def find_colmap_model(root: str | os.PathLike) -> Path | None:
    """The folder holding ``cameras.{bin,txt}`` under ``root``: ``root`` itself, ``root/sparse/0`` or
    ``root/sparse``; ``None`` if there is none."""
    root = Path(root)
    for folder in (root, root / "sparse" / "0", root / "sparse"):
        if (folder / "cameras.bin").is_file() or (folder / "cameras.txt").is_file():
            return folder
    return None


def read_colmap_model(folder: str | os.PathLike) -> ColmapModel:
    """Read a COLMAP sparse model, binary files first, else text files.

    Args:
        folder: the folder with ``cameras``, ``images`` and (optionally) ``points3D`` ``.bin`` or ``.txt``.

    Returns:
        The :class:`ColmapModel`.

    Raises:
        ColmapError: missing files, truncated or malformed data, unknown camera models, images referring to
            missing cameras.
    """
    folder = Path(folder)
    ext = ".bin" if (folder / "cameras.bin").is_file() else ".txt"
    readers = {".bin": (_read_cameras_bin, _read_images_bin, _read_points_bin),
               ".txt": (_read_cameras_txt, _read_images_txt, _read_points_txt)}[ext]
    for name in ("cameras", "images"):
        if not (folder / f"{name}{ext}").is_file():
            raise ColmapError(f"missing file: {folder / (name + ext)} (not a COLMAP sparse model)")
    try:
        cameras = readers[0](folder / f"cameras{ext}")
        images = readers[1](folder / f"images{ext}")
    except UnicodeDecodeError as exc:
        raise ColmapError(f"{folder}: a text file is not UTF-8 ({exc})") from None
    if (folder / f"points3D{ext}").is_file():
        points, colors = readers[2](folder / f"points3D{ext}")
    else:
        points, colors = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    for image in images:
        if image.camera_id not in cameras:
            raise ColmapError(f"{folder}: image {image.name!r} refers to camera {image.camera_id}, which is not "
                              f"in cameras{ext}")
    return ColmapModel(cameras, images, points, colors)


def write_colmap_model(folder: str | os.PathLike, model: ColmapModel, *, binary: bool = True) -> None:
    """Write a sparse model (without 2-D observations or tracks) as ``.bin`` or ``.txt`` files, atomically.

    Args:
        folder: destination folder (created if missing).
        model: the model.
        binary: write ``.bin`` files (else ``.txt``).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for cam in model.cameras.values():
        if cam.model not in _MODEL_IDS or len(cam.params) != _MODEL_IDS[cam.model][1]:
            raise ColmapError(f"camera {cam.camera_id}: {cam.model} with {len(cam.params)} parameters")
    if binary:
        cams = struct.pack("<Q", len(model.cameras)) + b"".join(
            struct.pack(f"<iiQQ{len(c.params)}d", c.camera_id, _MODEL_IDS[c.model][0], c.width, c.height, *c.params)
            for c in model.cameras.values())
        imgs = struct.pack("<Q", len(model.images)) + b"".join(
            struct.pack("<i7di", im.image_id, *im.qvec, *im.tvec, im.camera_id) + im.name.encode() + b"\0"
            + struct.pack("<Q", 0) for im in model.images)
        pts = struct.pack("<Q", len(model.points)) + b"".join(
            struct.pack("<Q3d3BdQ", i + 1, *map(float, p), *map(int, c), 0.0, 0)
            for i, (p, c) in enumerate(zip(model.points, model.colors)))
        files = {"cameras.bin": cams, "images.bin": imgs, "points3D.bin": pts}
    else:
        cams = "".join(f"{c.camera_id} {c.model} {c.width} {c.height} {' '.join(map(repr, c.params))}\n"
                       for c in model.cameras.values())
        imgs = "".join(f"{im.image_id} {' '.join(map(repr, (*im.qvec, *im.tvec)))} {im.camera_id} {im.name}\n\n"
                       for im in model.images)
        pts = "".join(f"{i + 1} {' '.join(repr(float(v)) for v in p)} {' '.join(str(int(v)) for v in c)} 0\n"
                      for i, (p, c) in enumerate(zip(model.points, model.colors)))
        header = "# written by gsw\n"
        files = {"cameras.txt": header + cams, "images.txt": header + imgs, "points3D.txt": header + pts}
    for name, content in files.items():
        with atomic_write(folder / name, "wb" if binary else "w") as f:
            f.write(content)
