"""Pinhole cameras in the OpenCV convention, with converters from NeRF/Blender and INRIA ``cameras.json``.

Conventions (see ``GUIDE.md`` section 3):

- ``viewmat`` is the 4x4 world-to-camera transform; camera axes are OpenCV's: x right, y down, z forward.
- Intrinsics ``fx, fy, cx, cy`` are in pixels. The image spans ``[0, W] x [0, H]`` and pixel ``(i, j)``
  (column ``i``, row ``j``) has its centre at ``(i + 0.5, j + 0.5)``, so a centred camera has
  ``cx = W / 2, cy = H / 2`` (the NeRF/Blender and gsplat convention, equal to the INRIA rasterizer's).
- A camera-space point ``(x, y, z)`` projects to ``u = fx * x / z + cx``, ``v = fy * y / z + cy``.
- Field-of-view angles are in radians unless the argument name ends in ``_deg``.
- Image sides are ``1..MAX_IMAGE_SIZE`` pixels (checked here, before a renderer allocates anything).

Camera files (INRIA ``cameras.json``) are read and written by :mod:`gsw.camera_io`;
``load_inria_cameras`` and ``save_inria_cameras`` stay importable from here.

Example:
    >>> import math, torch
    >>> from gsw.camera import Camera
    >>> cam = Camera.look_at((0, -4, 0), (0, 0, 0), (0, 0, 1), math.radians(60), 64, 48)
    >>> px, depth = cam.project(torch.tensor([[0.0, 0.0, 0.0]]))
    >>> px.tolist(), depth.tolist()
    ([[32.0, 24.0]], [4.0])
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Sequence, Union

import torch
from torch import Tensor

__all__ = [
    "Camera", "orbit_cameras", "stack_viewmats", "stack_Ks", "load_inria_cameras", "save_inria_cameras",
    "MAX_IMAGE_SIZE",
]

MAX_IMAGE_SIZE = 16384
"""Largest accepted image width or height, pixels (a 16384 x 16384 float RGB render is 3 GiB)."""

_ORTHO_TOL = 1e-4
_OPENGL_TO_OPENCV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))

Vec3 = Union[Sequence[float], Tensor]


def _vec3(value: Vec3, name: str) -> Tensor:
    t = torch.as_tensor(value, dtype=torch.float64).detach().cpu()
    if t.shape != (3,) or not torch.isfinite(t).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return t


def _mat4(value: Any, name: str) -> Tensor:
    t = torch.as_tensor(value)
    if t.shape != (4, 4):
        raise ValueError(f"{name} must have shape [4, 4], got {list(t.shape)}")
    return t if t.is_floating_point() else t.double()


def _rigid_inverse(m: Tensor) -> Tensor:
    """Inverse of a rigid 4x4 transform ``[[R, t], [0, 1]]``: ``[[R^T, -R^T t], [0, 1]]``."""
    out = torch.eye(4, dtype=m.dtype, device=m.device)
    rt = m[:3, :3].transpose(0, 1)
    out[:3, :3] = rt
    out[:3, 3] = -(rt @ m[:3, 3])
    return out


def _focal_from_fov(fov: float, size: int, name: str) -> float:
    if not 0.0 < fov < math.pi:
        raise ValueError(f"{name} must be in (0, pi) radians, got {fov!r}")
    return size / (2.0 * math.tan(fov / 2.0))


@dataclass(eq=False)
class Camera:
    """A pinhole camera.

    Attributes:
        viewmat: ``[4, 4]`` world-to-camera transform (OpenCV axes), float32 or float64.
        fx: focal length along x, pixels.
        fy: focal length along y, pixels.
        cx: principal point x, pixels (``W / 2`` when centred).
        cy: principal point y, pixels (``H / 2`` when centred).
        width: image width ``W``, pixels.
        height: image height ``H``, pixels.
        name: optional label (e.g. the image file name).
    """

    viewmat: Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    name: str = ""
    # Camera-to-world the camera was built from, used by ``c2w`` (and so ``to_inria``) while ``viewmat``
    # is unchanged, so that converting back is bit-exact rather than a rounded double inverse.
    _source: tuple[Tensor, Tensor] | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.viewmat, Tensor):
            raise ValueError(f"Camera.viewmat must be a torch.Tensor, got {type(self.viewmat).__name__}")
        v = self.viewmat
        if v.shape != (4, 4) or v.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"Camera.viewmat must be a [4, 4] float32/float64 tensor, got {list(v.shape)} {v.dtype}")
        if not torch.isfinite(v).all():
            raise ValueError("Camera.viewmat must be finite")
        vd = v.detach().double().cpu()
        if not torch.allclose(vd[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64), atol=_ORTHO_TOL):
            raise ValueError(f"Camera.viewmat last row must be [0, 0, 0, 1], got {vd[3].tolist()}")
        r = vd[:3, :3]
        err = float((r @ r.T - torch.eye(3, dtype=torch.float64)).abs().max())
        if err > _ORTHO_TOL:
            raise ValueError(f"Camera.viewmat rotation is not orthonormal (max |R R^T - I| = {err:.2e})")
        if float(torch.linalg.det(r)) < 0:
            raise ValueError("Camera.viewmat rotation has determinant -1 (a reflection, not a rotation)")
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            positive = name in ("fx", "fy")
            if (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)
                    or (positive and value <= 0)):
                kind = "a positive finite number" if positive else "a finite number"
                raise ValueError(f"Camera.{name} must be {kind}, got {value!r}")
            setattr(self, name, float(value))
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_IMAGE_SIZE:
                raise ValueError(f"Camera.{name} must be an int in 1..{MAX_IMAGE_SIZE}, got {value!r}")

    # ------------------------------------------------------------------ derived quantities
    @property
    def K(self) -> Tensor:  # noqa: N802 - the standard name
        """``[3, 3]`` intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, dtype/device of ``viewmat``."""
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
            dtype=self.viewmat.dtype,
            device=self.viewmat.device,
        )

    @property
    def R(self) -> Tensor:  # noqa: N802
        """``[3, 3]`` world-to-camera rotation."""
        return self.viewmat[:3, :3]

    @property
    def t(self) -> Tensor:
        """``[3]`` world-to-camera translation (the world origin in camera coordinates)."""
        return self.viewmat[:3, 3]

    @property
    def c2w(self) -> Tensor:
        """``[4, 4]`` camera-to-world transform (OpenCV axes); columns 0..2 are the camera's right, down and
        forward directions in world coordinates, column 3 its centre."""
        source = self._source
        v = self.viewmat
        if (
            source is not None
            and not v.requires_grad
            and (source[0].device, source[0].dtype) == (v.device, v.dtype)
            and torch.equal(source[0], v)
        ):
            return source[1].clone()
        return _rigid_inverse(self.viewmat)

    @property
    def center(self) -> Tensor:
        """``[3]`` camera centre, world frame."""
        return self.c2w[:3, 3]

    @property
    def fov_x(self) -> float:
        """Horizontal field of view, radians (assumes a centred principal point)."""
        return 2.0 * math.atan(self.width / (2.0 * self.fx))

    @property
    def fov_y(self) -> float:
        """Vertical field of view, radians (assumes a centred principal point)."""
        return 2.0 * math.atan(self.height / (2.0 * self.fy))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def _from_c2w(cls, c2w: Tensor, **kwargs: Any) -> "Camera":
        cam = cls(viewmat=_rigid_inverse(c2w), **kwargs)
        cam._source = (cam.viewmat.clone(), c2w.clone())
        return cam

    @classmethod
    def from_fov(
        cls,
        fov_x: float,
        width: int,
        height: int,
        *,
        viewmat: Tensor | None = None,
        c2w: Tensor | None = None,
        fov_y: float | None = None,
        name: str = "",
    ) -> "Camera":
        """A centred camera from its field of view.

        Args:
            fov_x: horizontal field of view, radians.
            width: image width, pixels.
            height: image height, pixels.
            viewmat: ``[4, 4]`` world-to-camera (OpenCV). Give at most one of ``viewmat`` and ``c2w``;
                identity if neither.
            c2w: ``[4, 4]`` camera-to-world (OpenCV).
            fov_y: vertical field of view, radians; default gives square pixels (``fy = fx``).
            name: label.

        Returns:
            The camera, ``cx = W / 2``, ``cy = H / 2``.
        """
        if viewmat is not None and c2w is not None:
            raise ValueError("give at most one of viewmat and c2w")
        fx = _focal_from_fov(fov_x, width, "fov_x")
        fy = fx if fov_y is None else _focal_from_fov(fov_y, height, "fov_y")
        kwargs = dict(fx=fx, fy=fy, cx=width / 2.0, cy=height / 2.0, width=width, height=height, name=name)
        if c2w is not None:
            return cls._from_c2w(_mat4(c2w, "c2w"), **kwargs)
        if viewmat is None:
            viewmat = torch.eye(4, dtype=torch.float64)
        return cls(viewmat=_mat4(viewmat, "viewmat"), **kwargs)

    @classmethod
    def from_nerf(
        cls,
        c2w_opengl: Tensor | Sequence[Sequence[float]],
        width: int,
        height: int,
        *,
        fov_x: float | None = None,
        fx: float | None = None,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
        name: str = "",
    ) -> "Camera":
        """A camera from a Blender/NeRF ``transform_matrix`` (camera-to-world, OpenGL axes: x right, y up,
        z backward).

        Args:
            c2w_opengl: ``[4, 4]`` camera-to-world in the OpenGL convention (``frames[i].transform_matrix``).
            width: image width, pixels.
            height: image height, pixels.
            fov_x: horizontal field of view, radians (``camera_angle_x``); or give ``fx``.
            fx: focal length x, pixels (instant-ngp ``fl_x``).
            fy: focal length y, pixels; default ``fx``.
            cx: principal point x; default ``W / 2``.
            cy: principal point y; default ``H / 2``.
            name: label (e.g. ``file_path``).

        Returns:
            The camera in the OpenCV convention (the y and z camera axes flipped).
        """
        if (fov_x is None) == (fx is None):
            raise ValueError("give exactly one of fov_x and fx")
        if fx is None:
            fx = _focal_from_fov(fov_x, width, "fov_x")
        c2w = _mat4(c2w_opengl, "c2w_opengl")
        c2w = (c2w.double() @ _OPENGL_TO_OPENCV).to(c2w.dtype)
        return cls._from_c2w(
            c2w,
            fx=fx,
            fy=fx if fy is None else fy,
            cx=width / 2.0 if cx is None else cx,
            cy=height / 2.0 if cy is None else cy,
            width=width,
            height=height,
            name=name,
        )

    @classmethod
    def from_inria(cls, entry: dict[str, Any]) -> "Camera":
        """A camera from one INRIA ``cameras.json`` entry; see :func:`gsw.camera_io.camera_from_inria`."""
        from gsw.camera_io import camera_from_inria  # noqa: PLC0415 - camera_io imports this module

        return camera_from_inria(entry)

    def to_inria(self, id: int) -> dict[str, Any]:  # noqa: A002 - the JSON key
        """This camera as an INRIA ``cameras.json`` entry; see :func:`gsw.camera_io.camera_to_inria`."""
        from gsw.camera_io import camera_to_inria  # noqa: PLC0415

        return camera_to_inria(self, id)

    @classmethod
    def look_at(
        cls,
        eye: Vec3,
        target: Vec3,
        up: Vec3,
        fov_x: float,
        width: int,
        height: int,
        *,
        fov_y: float | None = None,
        name: str = "",
    ) -> "Camera":
        """A centred camera at ``eye`` looking at ``target``, with ``up`` appearing upwards in the image.

        Args:
            eye: ``[3]`` camera centre, world frame.
            target: ``[3]`` point on the optical axis, world frame (projects to ``(cx, cy)``).
            up: ``[3]`` world direction that appears up (smaller ``v``) in the image.
            fov_x: horizontal field of view, radians.
            width: image width, pixels.
            height: image height, pixels.
            fov_y: vertical field of view, radians; default gives square pixels.
            name: label.

        Returns:
            The camera (float64 ``viewmat``).

        Raises:
            ValueError: if ``eye == target`` or ``up`` is parallel to the viewing direction.
        """
        eye_t, target_t, up_t = _vec3(eye, "eye"), _vec3(target, "target"), _vec3(up, "up")
        forward = target_t - eye_t
        if forward.norm() < 1e-12:
            raise ValueError("look_at: eye and target coincide")
        forward = forward / forward.norm()
        right = torch.linalg.cross(forward, up_t)
        if right.norm() < 1e-9 * max(float(up_t.norm()), 1e-300):
            raise ValueError("look_at: up is parallel to the viewing direction (or zero)")
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye_t
        return cls.from_fov(fov_x, width, height, c2w=c2w, fov_y=fov_y, name=name)

    # ------------------------------------------------------------------ methods
    def scaled(self, factor: float) -> "Camera":
        """The same camera for a resized image.

        The new size is ``round(W * factor) x round(H * factor)`` (at least 1); intrinsics scale by the
        actual size ratios, which keeps the image-edge convention (``[0, W]`` maps onto ``[0, W']``).

        Args:
            factor: resize factor, > 0 (0.5 halves the resolution).

        Returns:
            A new camera with the same ``viewmat``.
        """
        if not factor > 0 or not math.isfinite(factor):
            raise ValueError(f"scale factor must be positive and finite, got {factor!r}")
        width = max(1, round(self.width * factor))
        height = max(1, round(self.height * factor))
        sx, sy = width / self.width, height / self.height
        cam = replace(
            self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=width, height=height
        )
        cam._source = self._source
        return cam

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project world points to pixel coordinates.

        Args:
            points: ``[N, 3]`` world positions.

        Returns:
            ``pixels [N, 2]`` as ``(u, v)`` with ``u = fx x / z + cx``, ``v = fy y / z + cy`` in the image-edge
            convention (the pixel ``(i, j)`` covers ``[i, i+1] x [j, j+1]``), and ``depth [N]``, the camera-space
            ``z``. Points with ``depth <= 0`` are behind the camera and their pixels meaningless. Computed in
            the promoted dtype of ``points`` and ``viewmat``, returned in ``points``' dtype.
        """
        if points.dim() != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape [N, 3], got {list(points.shape)}")
        dtype = torch.promote_types(points.dtype, self.viewmat.dtype)
        v = self.viewmat.to(device=points.device, dtype=dtype)
        cam = points.to(dtype) @ v[:3, :3].T + v[:3, 3]
        z = cam[:, 2]
        u = self.fx * cam[:, 0] / z + self.cx
        w = self.fy * cam[:, 1] / z + self.cy
        return torch.stack([u, w], dim=1).to(points.dtype), z.to(points.dtype)


# ---------------------------------------------------------------------------------------------- helpers


def orbit_cameras(
    center: Vec3,
    radius: float,
    n: int,
    *,
    width: int,
    height: int,
    elevation_deg: float = 30.0,
    fov_x_deg: float = 50.0,
    up: Vec3 = (0.0, 0.0, 1.0),
    azimuth_offset_deg: float = 0.0,
) -> list[Camera]:
    """``n`` cameras evenly spaced on a horizontal circle around ``center``, all looking at it.

    Camera ``k`` sits at azimuth ``azimuth_offset_deg + 360 k / n`` degrees, measured from the first
    horizontal basis vector ``e1`` (world x for ``up = +z``) towards ``e2 = up x e1`` (world y), at
    ``elevation_deg`` above the horizontal plane through ``center``.

    Args:
        center: ``[3]`` orbit centre, world frame.
        radius: distance of every camera from ``center``.
        n: number of cameras.
        width: image width, pixels.
        height: image height, pixels.
        elevation_deg: elevation above the plane orthogonal to ``up``, degrees (in ``(-90, 90)``).
        fov_x_deg: horizontal field of view, degrees.
        up: world up direction.
        azimuth_offset_deg: azimuth of the first camera, degrees.

    Returns:
        ``n`` cameras named ``orbit_000`` ..., float64 ``viewmat``; deterministic.
    """
    if n < 1 or radius <= 0:
        raise ValueError(f"orbit_cameras needs n >= 1 and radius > 0, got n={n}, radius={radius}")
    if not -90.0 < elevation_deg < 90.0:
        raise ValueError(f"elevation_deg must be in (-90, 90), got {elevation_deg}")
    c, u = _vec3(center, "center"), _vec3(up, "up")
    u = u / u.norm()
    axis = torch.eye(3, dtype=torch.float64)[0 if abs(float(u[0])) < 0.9 else 1]
    e1 = axis - (axis @ u) * u
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(u, e1)
    el = math.radians(elevation_deg)
    cams = []
    for k in range(n):
        az = math.radians(azimuth_offset_deg + 360.0 * k / n)
        direction = math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * u
        cams.append(
            Camera.look_at(
                c + radius * direction, c, u, math.radians(fov_x_deg), width, height, name=f"orbit_{k:03d}"
            )
        )
    return cams


def stack_viewmats(
    cameras: Sequence[Camera], *, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> Tensor:
    """Stack world-to-camera matrices for a batched rasterizer call.

    Args:
        cameras: ``C`` cameras.
        dtype: output dtype.
        device: output device (default CPU).

    Returns:
        ``[C, 4, 4]`` viewmats.
    """
    if not cameras:
        raise ValueError("stack_viewmats needs at least one camera")
    return torch.stack([c.viewmat.detach().to(device="cpu", dtype=torch.float64) for c in cameras]).to(
        device=device, dtype=dtype
    )


def stack_Ks(  # noqa: N802
    cameras: Sequence[Camera], *, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> Tensor:
    """Stack intrinsic matrices for a batched rasterizer call.

    Args:
        cameras: ``C`` cameras.
        dtype: output dtype.
        device: output device (default CPU).

    Returns:
        ``[C, 3, 3]`` intrinsics.
    """
    if not cameras:
        raise ValueError("stack_Ks needs at least one camera")
    return torch.tensor(
        [[[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]] for c in cameras], dtype=dtype, device=device
    )


def __getattr__(name: str) -> Any:
    """``load_inria_cameras`` / ``save_inria_cameras`` live in :mod:`gsw.camera_io` (imported on first use)."""
    if name in ("load_inria_cameras", "save_inria_cameras"):
        from gsw import camera_io  # noqa: PLC0415

        return getattr(camera_io, name)
    raise AttributeError(f"module 'gsw.camera' has no attribute {name!r}")
