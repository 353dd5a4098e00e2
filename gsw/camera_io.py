"""Camera JSON files: INRIA ``cameras.json`` reading/writing and the type-checked JSON field readers that
every camera file loader uses (INRIA here, NeRF/instant-ngp ``transforms*.json`` in :mod:`gsw.data.loaders`).

Fields are type-checked, never coerced: an integer field (``width``, ``height``, ``id``) takes an ``int`` or
an integral float (``800.0``, as instant-ngp's ``colmap2nerf.py`` writes) and rejects ``128.9``; a number
field rejects booleans, strings, lists and ``null``; every message names the file, the camera index and
the field. Files must be UTF-8 JSON. Image sizes are limited to :data:`gsw.camera.MAX_IMAGE_SIZE` before
anything is allocated for them.

Example:
    >>> from gsw.camera_io import load_inria_cameras
    >>> cams = load_inria_cameras("model/cameras.json")  # doctest: +SKIP
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Sequence

import torch

from gsw._atomic import atomic_write
from gsw.camera import MAX_IMAGE_SIZE, Camera

__all__ = [
    "CameraFileError", "read_json", "json_number", "json_integer", "json_matrix", "camera_from_inria",
    "camera_to_inria", "load_inria_cameras", "save_inria_cameras",
]

_MISSING = object()


def _show(value: Any) -> str:
    """``repr(value)`` and its type, shortened for messages."""
    text = repr(value)
    return f"{text[:60]}...{text[-10:]}" if len(text) > 80 else text


class CameraFileError(ValueError):
    """A camera file (INRIA ``cameras.json``) is unreadable, malformed or has a field of the wrong type."""


def read_json(path: str | os.PathLike, error: type[ValueError] = CameraFileError) -> Any:
    """Parse a UTF-8 JSON file (a UTF-8 byte-order mark is accepted).

    Args:
        path: the file.
        error: the exception class to raise (a ``ValueError`` subclass).

    Returns:
        The parsed JSON value.

    Raises:
        error: the path is missing or a directory, the file is not UTF-8 or not valid JSON; the message
            names the file.
    """
    path = Path(path)
    if path.is_dir():
        raise error(f"{path}: is a directory, expected a JSON file")
    if not path.is_file():
        raise error(f"missing file: {path}")
    data = path.read_bytes()
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text (byte {exc.start}: {data[exc.start:exc.start + 1]!r}); "
                    "JSON files must be UTF-8") from None
    try:
        return json.loads(text)
    except RecursionError:
        raise error(f"malformed JSON in {path}: nested too deeply") from None
    except ValueError as exc:  # JSONDecodeError, or an integer literal too long to convert
        raise error(f"malformed JSON in {path}: {exc}") from None


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_finite_number(value: Any) -> bool:
    """An int or float (not a bool) that converts to a finite float (``10**400`` does not)."""
    if not _is_number(value):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an int beyond the float range
        return False


def json_number(obj: dict, key: str, context: str, default: Any = _MISSING, *,
                error: type[ValueError] = CameraFileError, positive: bool = False) -> Any:
    """``obj[key]`` as a finite float (booleans, strings, lists and ``null`` are errors).

    Args:
        obj: the JSON object.
        key: the field.
        context: message prefix (file and camera index).
        default: returned when the key is absent; without it the key is required.
        error: exception class to raise.
        positive: also require ``> 0``.

    Returns:
        The float, or ``default``.
    """
    if key not in obj:
        if default is _MISSING:
            raise error(f"{context}: missing field {key!r}")
        return default
    value = obj[key]
    if not _is_finite_number(value) or (positive and value <= 0):
        kind = "a positive finite number" if positive else "a finite number"
        raise error(f"{context}: field {key!r} must be {kind}, got {_show(value)} ({type(value).__name__})")
    return float(value)


def json_integer(obj: dict, key: str, context: str, default: Any = _MISSING, *,
                 error: type[ValueError] = CameraFileError, low: int = 1, high: int = MAX_IMAGE_SIZE) -> Any:
    """``obj[key]`` as an int in ``[low, high]``; an integral float (``800.0``) counts, ``128.9`` does not.

    Args:
        obj: the JSON object.
        key: the field.
        context: message prefix.
        default: returned when the key is absent; without it the key is required.
        error: exception class to raise.
        low: smallest accepted value.
        high: largest accepted value (default the image size limit).

    Returns:
        The int, or ``default``.
    """
    if key not in obj:
        if default is _MISSING:
            raise error(f"{context}: missing field {key!r}")
        return default
    value = obj[key]
    if not _is_finite_number(value) or value != int(value):
        raise error(f"{context}: field {key!r} must be an integer, got {_show(value)} ({type(value).__name__})")
    if not low <= value <= high:
        raise error(f"{context}: field {key!r} = {int(value)} is outside {low}..{high}")
    return int(value)


def json_matrix(value: Any, shape: tuple[int, ...], name: str, context: str, *,
                error: type[ValueError] = CameraFileError) -> torch.Tensor:
    """A nested JSON list of finite numbers with exactly ``shape`` as a float64 tensor.

    Raises:
        error: wrong nesting/length, or an element that is not a finite number (booleans included).
    """
    def check(v: Any, dims: tuple[int, ...]) -> bool:
        if not dims:
            return _is_finite_number(v)
        return isinstance(v, list) and len(v) == dims[0] and all(check(x, dims[1:]) for x in v)

    if not check(value, shape):
        text = "x".join(map(str, shape))
        raise error(f"{context}: field {name!r} must be a {text} list of finite numbers, got {_show(value)}")
    return torch.tensor(value, dtype=torch.float64)


def camera_from_inria(entry: Any, context: str = "INRIA camera entry") -> Camera:
    """A camera from one entry of an INRIA ``cameras.json`` (also :meth:`gsw.camera.Camera.from_inria`).

    Args:
        entry: ``{"id", "img_name", "width", "height", "position" [3], "rotation" [3][3], "fx", "fy"}``;
            ``rotation`` is the camera-to-world rotation (rows, OpenCV axes), ``position`` the camera centre.
        context: message prefix (the file and the camera index).

    Returns:
        The camera (float64 ``viewmat``, ``name = img_name``; ``cx = W / 2``, ``cy = H / 2`` unless the entry
        carries the optional ``cx`` / ``cy`` keys written by :func:`camera_to_inria`).

    Raises:
        CameraFileError: naming the field: a missing or mistyped field, a size outside
            ``1..MAX_IMAGE_SIZE``, or a rotation that is not a rotation.
    """
    if not isinstance(entry, dict):
        raise CameraFileError(f"{context}: expected a JSON object, got {type(entry).__name__}")
    missing = [k for k in ("width", "height", "position", "rotation", "fx", "fy") if k not in entry]
    if missing:
        raise CameraFileError(f"{context}: lacks {', '.join(missing)}")
    if "id" in entry:
        json_integer(entry, "id", context, low=-(2**63), high=2**63 - 1)
    name = entry.get("img_name", "")
    if not isinstance(name, str):
        raise CameraFileError(f"{context}: field 'img_name' must be a string, got {_show(name)}")
    width, height = json_integer(entry, "width", context), json_integer(entry, "height", context)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = json_matrix(entry["rotation"], (3, 3), "rotation", context)
    c2w[:3, 3] = json_matrix(entry["position"], (3,), "position", context)
    try:
        return Camera._from_c2w(
            c2w,
            fx=json_number(entry, "fx", context, positive=True),
            fy=json_number(entry, "fy", context, positive=True),
            cx=json_number(entry, "cx", context, width / 2.0),
            cy=json_number(entry, "cy", context, height / 2.0),
            width=width, height=height, name=name,
        )
    except CameraFileError:
        raise
    except ValueError as exc:  # the fields are checked above: what is left is the rotation itself
        raise CameraFileError(f"{context}: field 'rotation' is not a rotation: {exc}") from None


def camera_to_inria(camera: Camera, id: int) -> dict[str, Any]:  # noqa: A002 - the JSON key
    """A camera as an INRIA ``cameras.json`` entry (inverse of :func:`camera_from_inria`).

    Args:
        camera: the camera.
        id: the entry's ``id``.

    Returns:
        ``{"id", "img_name", "width", "height", "position", "rotation", "fy", "fx"}`` with plain Python numbers,
        plus ``cx`` / ``cy`` when the principal point is off-centre (INRIA's format assumes the centre; its
        tools ignore the extra keys, :func:`camera_from_inria` reads them back).
    """
    c2w = camera.c2w.detach().double().cpu()
    off_centre = (abs(camera.cx - camera.width / 2.0) > 1e-6 * camera.width
                  or abs(camera.cy - camera.height / 2.0) > 1e-6 * camera.height)
    return {
        "id": id,
        "img_name": camera.name,
        "width": camera.width,
        "height": camera.height,
        "position": c2w[:3, 3].tolist(),
        "rotation": c2w[:3, :3].tolist(),
        "fy": camera.fy,
        "fx": camera.fx,
        **({"cx": camera.cx, "cy": camera.cy} if off_centre else {}),
    }


def load_inria_cameras(path: str | os.PathLike) -> list[Camera]:
    """Read an INRIA ``cameras.json`` (a non-empty list of entries, see :func:`camera_from_inria`).

    Args:
        path: the JSON file.

    Returns:
        The cameras, in file order.

    Raises:
        CameraFileError: the file is missing, a directory, not UTF-8, not JSON, not a non-empty list, or an
            entry is malformed (the message names the file, the camera index and the field).
    """
    entries = read_json(path)
    if not isinstance(entries, list) or not entries:
        raise CameraFileError(f"{path}: expected a non-empty JSON list of camera entries, "
                              f"got {type(entries).__name__}{' (empty)' if entries == [] else ''}")
    return [camera_from_inria(e, f"{path}: camera {k}") for k, e in enumerate(entries)]


def save_inria_cameras(cameras: Sequence[Camera], path: str | os.PathLike) -> None:
    """Write cameras as an INRIA ``cameras.json`` (ids ``0..C-1``), atomically.

    Args:
        cameras: the cameras.
        path: destination file.
    """
    entries = [camera_to_inria(cam, i) for i, cam in enumerate(cameras)]
    with atomic_write(path, "w") as f:
        json.dump(entries, f, indent=1)
