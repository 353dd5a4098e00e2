"""OpenCV radial-tangential lens distortion (``k1, k2, p1, p2[, k3]``) and image undistortion with torch.

Model (normalised camera coordinates ``x = (u - cx) / fx``, ``y = (v - cy) / fy``, ``r^2 = x^2 + y^2``)::

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y

This is what COLMAP's ``OPENCV`` camera and instant-ngp's ``transforms.json`` (``k1, k2, p1, p2``) store.
Pixel coordinates follow :mod:`gsw.camera`: the image spans ``[0, W] x [0, H]`` and pixel ``(i, j)`` has its
centre at ``(i + 0.5, j + 0.5)``.

Undistorting an image needs only the forward model: every pixel of the undistorted (pinhole) image is mapped
through :func:`distort_normalized` into the captured image and sampled bilinearly (``grid_sample``).
:func:`undistort_normalized` is the iterative inverse, for points.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["Distortion", "distort_normalized", "undistort_normalized", "distort_pixels", "undistort_pixels",
           "undistort_image"]


@dataclass(frozen=True)
class Distortion:
    """OpenCV radial-tangential coefficients."""

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    @property
    def is_identity(self) -> bool:
        """True when every coefficient is zero."""
        return not any((self.k1, self.k2, self.p1, self.p2, self.k3))


def distort_normalized(xy: Tensor, d: Distortion) -> Tensor:
    """Apply the distortion to ``[..., 2]`` normalised coordinates."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))
    xd = x * radial + 2.0 * d.p1 * x * y + d.p2 * (r2 + 2.0 * x * x)
    yd = y * radial + d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * x * y
    return torch.stack([xd, yd], dim=-1)


def undistort_normalized(xy_d: Tensor, d: Distortion, *, iterations: int = 20) -> Tensor:
    """Invert :func:`distort_normalized` by Gauss-Newton iterations (2x2 Jacobian per point).

    Args:
        xy_d: ``[..., 2]`` distorted normalised coordinates.
        d: the coefficients.
        iterations: Newton steps (converges in a few for realistic lenses).

    Returns:
        ``[..., 2]`` undistorted normalised coordinates.
    """
    xy = xy_d.clone()
    for _ in range(iterations):
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))
        dradial = d.k1 + r2 * (2.0 * d.k2 + 3.0 * d.k3 * r2)  # d radial / d r2
        err = distort_normalized(xy, d) - xy_d
        # Jacobian of (xd, yd) w.r.t. (x, y)
        j00 = radial + 2.0 * x * x * dradial + 2.0 * d.p1 * y + 6.0 * d.p2 * x
        j01 = 2.0 * x * y * dradial + 2.0 * d.p1 * x + 2.0 * d.p2 * y
        j10 = 2.0 * x * y * dradial + 2.0 * d.p1 * x + 2.0 * d.p2 * y
        j11 = radial + 2.0 * y * y * dradial + 6.0 * d.p1 * y + 2.0 * d.p2 * x
        det = j00 * j11 - j01 * j10
        dx = (j11 * err[..., 0] - j01 * err[..., 1]) / det
        dy = (-j10 * err[..., 0] + j00 * err[..., 1]) / det
        xy = xy - torch.stack([dx, dy], dim=-1)
    return xy


def distort_pixels(uv: Tensor, fx: float, fy: float, cx: float, cy: float, d: Distortion) -> Tensor:
    """Map ``[..., 2]`` ideal pinhole pixel coordinates to distorted (captured) pixel coordinates."""
    c = uv.new_tensor([cx, cy])
    f = uv.new_tensor([fx, fy])
    return distort_normalized((uv - c) / f, d) * f + c


def undistort_pixels(uv_d: Tensor, fx: float, fy: float, cx: float, cy: float, d: Distortion) -> Tensor:
    """Map ``[..., 2]`` distorted pixel coordinates to ideal pinhole pixel coordinates (inverse of
    :func:`distort_pixels`)."""
    c = uv_d.new_tensor([cx, cy])
    f = uv_d.new_tensor([fx, fy])
    return undistort_normalized((uv_d - c) / f, d) * f + c


def undistort_image(image: Tensor, fx: float, fy: float, cx: float, cy: float, d: Distortion) -> Tensor:
    """Resample a captured (distorted) image into the ideal pinhole camera with the same intrinsics.

    Args:
        image: ``[C, H, W]`` or ``[B, C, H, W]`` float image.
        fx: focal length x, pixels.
        fy: focal length y, pixels.
        cx: principal point x, pixels.
        cy: principal point y, pixels.
        d: the distortion of the captured image.

    Returns:
        The undistorted image, same shape. Pixels whose source falls outside the capture are 0 (an alpha
        channel, if present, is therefore 0 there too).
    """
    squeeze = image.dim() == 3
    x = image[None] if squeeze else image
    h, w = x.shape[-2:]
    dtype = torch.float64
    jj, ii = torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")
    uv = torch.stack([ii + 0.5, jj + 0.5], dim=-1)
    src = distort_pixels(uv, fx, fy, cx, cy, d)
    grid = torch.stack([2.0 * src[..., 0] / w - 1.0, 2.0 * src[..., 1] / h - 1.0], dim=-1)
    grid = grid.to(x.dtype).to(x.device)[None].expand(x.shape[0], -1, -1, -1)
    out = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return out[0] if squeeze else out
