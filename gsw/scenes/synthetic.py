"""Deterministic synthetic scenes: random Gaussians, a benchmark frustum scene and a textured default scene.

Every generator draws from its own seeded CPU ``torch.Generator`` in float64 (independent of the global RNG,
the target dtype and the device), then casts. World frame: z is up.

Example:
    >>> from gsw.scenes import random_gaussians, default_scene
    >>> g = random_gaussians(100, sh_degree=1, seed=3)
    >>> len(g), g.sh_degree
    (100, 1)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from gsw.camera import Camera, orbit_cameras
from gsw.gaussians import Gaussians, rgb_to_sh_dc, sh_degree_to_num_coeffs

__all__ = [
    "SyntheticScene", "random_gaussians", "frustum_scene", "frustum_sigma_px", "heavy_scene", "default_scene",
    "default_cameras", "DEFAULT_SCENE_CENTER",
]

DEFAULT_SCENE_CENTER = (0.0, 0.0, 0.4)
"""World point the default cameras orbit and look at."""

_F64 = torch.float64


@dataclass
class SyntheticScene:
    """A generated scene.

    Attributes:
        gaussians: the model.
        cameras: views of it.
        background: ``[3]`` RGB background colour in ``[0, 1]`` (same dtype/device as the Gaussians).
    """

    gaussians: Gaussians
    cameras: list[Camera]
    background: Tensor


def _generator(seed: int) -> torch.Generator:
    return torch.Generator(device="cpu").manual_seed(int(seed))


def _uniform(gen: torch.Generator, shape: Sequence[int], low: float = 0.0, high: float = 1.0) -> Tensor:
    return low + (high - low) * torch.rand(*shape, generator=gen, dtype=_F64)


def _normal(gen: torch.Generator, shape: Sequence[int], std: float = 1.0) -> Tensor:
    return std * torch.randn(*shape, generator=gen, dtype=_F64)


def _sh_from_rgb(gen: torch.Generator, rgb: Tensor, sh_degree: int, rest_std: float) -> Tensor:
    """``[N, K, 3]`` SH with the given base colour and small random higher orders."""
    k = sh_degree_to_num_coeffs(sh_degree)
    sh = _normal(gen, (rgb.shape[0], k, 3), rest_std)
    sh[:, 0] = rgb_to_sh_dc(rgb)
    return sh


def _make(params: dict[str, Tensor], dtype: torch.dtype, device: torch.device | str | None) -> Gaussians:
    return Gaussians(**{k: v.to(device=device, dtype=dtype).contiguous() for k, v in params.items()})


def random_gaussians(
    n: int,
    *,
    sh_degree: int = 3,
    seed: int = 0,
    extent: float = 1.0,
    scale_range: tuple[float, float] = (0.01, 0.1),
    opacity_range: tuple[float, float] = (0.05, 0.95),
    sh_rest_std: float = 0.1,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Gaussians:
    """Random Gaussians in the cube ``[-extent, extent]^3`` centred at the origin.

    Args:
        n: number of Gaussians.
        sh_degree: SH degree in ``0..3``.
        seed: RNG seed.
        extent: half side of the cube holding the means, world units.
        scale_range: per-axis standard deviations are log-uniform in this range, world units.
        opacity_range: opacities are uniform in this range (``0 < low <= high < 1``).
        sh_rest_std: standard deviation of the ``f_rest`` coefficients (DC gives a uniform random colour).
        dtype: output dtype.
        device: output device.

    Returns:
        ``n`` Gaussians with uniformly random rotations.
    """
    lo, hi = scale_range
    if not 0 < lo <= hi:
        raise ValueError(f"scale_range must satisfy 0 < low <= high, got {scale_range}")
    olo, ohi = opacity_range
    if not 0 < olo <= ohi < 1:
        raise ValueError(f"opacity_range must satisfy 0 < low <= high < 1, got {opacity_range}")
    gen = _generator(seed)
    means = _uniform(gen, (n, 3), -extent, extent)
    log_scales = _uniform(gen, (n, 3), math.log(lo), math.log(hi))
    quats = _normal(gen, (n, 4))
    opacity_logits = torch.logit(_uniform(gen, (n,), olo, ohi))
    sh = _sh_from_rgb(gen, _uniform(gen, (n, 3)), sh_degree, sh_rest_std)
    return _make(
        dict(means=means, log_scales=log_scales, quats=quats, opacity_logits=opacity_logits, sh=sh), dtype, device
    )


def frustum_sigma_px(n: int, width: int, height: int, coverage: float = 4.0) -> float:
    """Mean projected standard deviation (pixels) of the Gaussians of :func:`frustum_scene`.

    Chosen so that the 1-sigma discs of all ``n`` Gaussians cover the image ``coverage`` times:
    ``n * pi * sigma^2 = coverage * W * H``. For 100k Gaussians at 800x800 and ``coverage = 4`` this is
    2.85 px (a 3-sigma footprint radius of ~8.6 px), about what a trained 3DGS scene looks like.

    Args:
        n: number of Gaussians.
        width: image width, pixels.
        height: image height, pixels.
        coverage: how many times the 1-sigma discs cover the image.

    Returns:
        sigma in pixels.
    """
    return math.sqrt(coverage * width * height / (math.pi * max(n, 1)))


def _frustum_points(gen: torch.Generator, camera: Camera, z: Tensor) -> Tensor:
    """World points at camera-space depths ``z`` [n] and uniform pixel positions (drawn from ``gen``): [n, 3]."""
    n = z.shape[0]
    u = _uniform(gen, (n,), 0.0, camera.width)
    v = _uniform(gen, (n,), 0.0, camera.height)
    cam_points = torch.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], dim=1)
    c2w = camera.c2w.detach().to(device="cpu", dtype=_F64)
    return cam_points @ c2w[:3, :3].T + c2w[:3, 3]


def frustum_scene(
    n: int,
    camera: Camera,
    *,
    sh_degree: int = 3,
    seed: int = 0,
    depth_range: tuple[float, float] = (2.0, 10.0),
    coverage: float = 4.0,
    sh_rest_std: float = 0.1,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Gaussians:
    """The benchmark scene: Gaussians uniformly distributed in the camera frustum between two depths.

    Means are uniform in the frustum volume (depth density ``~ z^2``, pixel position uniform over the
    image). World scales are ``sigma_px * z / f`` (``f = sqrt(fx fy)``, ``sigma_px`` from
    :func:`frustum_sigma_px`), so every Gaussian projects to about ``sigma_px`` pixels whatever its depth,
    times a log-normal size factor (std 0.3) and a log-normal per-axis anisotropy (std 0.3). Opacity logits
    are ``N(0, 1)``; colours are uniform random with DC-dominant SH (``f_rest ~ N(0, sh_rest_std)``).

    Args:
        n: number of Gaussians.
        camera: the camera whose frustum is filled.
        sh_degree: SH degree in ``0..3``.
        seed: RNG seed.
        depth_range: ``(near, far)`` camera-space depths, ``0 < near < far``.
        coverage: image coverage of the 1-sigma discs (see :func:`frustum_sigma_px`).
        sh_rest_std: standard deviation of the ``f_rest`` coefficients.
        dtype: output dtype.
        device: output device.

    Returns:
        ``n`` Gaussians in world coordinates.
    """
    near, far = depth_range
    if not 0 < near < far:
        raise ValueError(f"depth_range must satisfy 0 < near < far, got {depth_range}")
    gen = _generator(seed)
    z = (near**3 + _uniform(gen, (n,)) * (far**3 - near**3)) ** (1.0 / 3.0)
    means = _frustum_points(gen, camera, z)

    sigma = frustum_sigma_px(n, camera.width, camera.height, coverage) / math.sqrt(camera.fx * camera.fy)
    log_scales = (torch.log(sigma * z) + _normal(gen, (n,), 0.3))[:, None] + _normal(gen, (n, 3), 0.3)
    quats = _normal(gen, (n, 4))
    opacity_logits = _normal(gen, (n,))
    sh = _sh_from_rgb(gen, _uniform(gen, (n, 3)), sh_degree, sh_rest_std)
    return _make(
        dict(means=means, log_scales=log_scales, quats=quats, opacity_logits=opacity_logits, sh=sh), dtype, device
    )


def heavy_scene(
    n: int,
    camera: Camera,
    *,
    sh_degree: int = 3,
    seed: int = 0,
    depth_range: tuple[float, float] = (2.0, 12.0),
    log_scale_mean: float = -4.6,
    log_scale_std: float = 0.5,
    sh_rest_std: float = 0.1,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Gaussians:
    """A heavier benchmark scene than :func:`frustum_scene`: larger Gaussians, wide opacity spread.

    Means have a uniform pixel position and a depth ``z`` uniform in ``depth_range``; each Gaussian is
    isotropic with world scale ``exp(N(log_scale_mean, log_scale_std)) * 0.5 * z`` (so its projected size
    does not depend on its depth); opacity logits are ``N(0, 2)``; the DC SH coefficients are uniform in
    ``[-1, 1]`` and ``f_rest ~ N(0, sh_rest_std)``. The benchmarks use it with a 60 degree horizontal field of
    view (``Camera.from_fov(math.radians(60), W, H)``).

    Args:
        n: number of Gaussians.
        camera: the camera whose frustum is filled.
        sh_degree: SH degree in ``0..3``.
        seed: RNG seed.
        depth_range: ``(near, far)`` camera-space depths, ``0 < near < far``.
        log_scale_mean: mean of the log scale factor.
        log_scale_std: standard deviation of the log scale factor.
        sh_rest_std: standard deviation of the ``f_rest`` coefficients.
        dtype: output dtype.
        device: output device.

    Returns:
        ``n`` Gaussians in world coordinates.
    """
    near, far = depth_range
    if not 0 < near < far:
        raise ValueError(f"depth_range must satisfy 0 < near < far, got {depth_range}")
    gen = _generator(seed)
    z = _uniform(gen, (n,), near, far)
    means = _frustum_points(gen, camera, z)
    log_scales = (log_scale_mean + _normal(gen, (n,), log_scale_std) + torch.log(0.5 * z))[:, None].expand(n, 3)
    quats = _normal(gen, (n, 4))
    opacity_logits = _normal(gen, (n,), 2.0)
    k = sh_degree_to_num_coeffs(sh_degree)
    sh = _normal(gen, (n, k, 3), sh_rest_std)
    sh[:, 0] = _uniform(gen, (n, 3), -1.0, 1.0)
    return _make(
        dict(means=means, log_scales=log_scales, quats=quats, opacity_logits=opacity_logits, sh=sh), dtype, device
    )


# ---------------------------------------------------------------------------------------------- default scene


def _quats_z_to(normals: Tensor) -> Tensor:
    """``[N, 4]`` unit quaternions (w, x, y, z) rotating the local z axis onto unit ``normals [N, 3]``."""
    q = torch.stack(
        [1.0 + normals[:, 2], -normals[:, 1], normals[:, 0], torch.zeros_like(normals[:, 0])], dim=1
    )
    flipped = q.norm(dim=1) < 1e-9  # normal == -z: rotate by pi about x
    q[flipped] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=q.dtype)
    return q / q.norm(dim=1, keepdim=True)


def _surfels(points: Tensor, normals: Tensor, rgb: Tensor, spacing: float) -> dict[str, Tensor]:
    """Flat Gaussians (discs) tangent to a surface sampled every ``spacing`` world units."""
    n = points.shape[0]
    log_scales = torch.tensor([0.7 * spacing, 0.7 * spacing, 0.05 * spacing], dtype=_F64).log().expand(n, 3)
    return dict(means=points, log_scales=log_scales.clone(), quats=_quats_z_to(normals), rgb=rgb.clamp(0, 1))


def _fibonacci_sphere(n: int) -> Tensor:
    """``[n, 3]`` nearly uniform unit vectors (Fibonacci lattice)."""
    i = torch.arange(n, dtype=_F64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = (1.0 - z * z).clamp_min(0).sqrt()
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack([r * phi.cos(), r * phi.sin(), z], dim=1)


def _ground(spacing: float, half: float = 2.5, square: float = 0.5) -> dict[str, Tensor]:
    ticks = torch.arange(-half + spacing / 2, half, spacing, dtype=_F64)
    x, y = torch.meshgrid(ticks, ticks, indexing="ij")
    x, y = x.reshape(-1), y.reshape(-1)
    points = torch.stack([x, y, torch.zeros_like(x)], dim=1)
    parity = (torch.floor(x / square) + torch.floor(y / square)).remainder(2)[:, None]
    light, dark = torch.tensor([0.9, 0.88, 0.8], dtype=_F64), torch.tensor([0.2, 0.25, 0.3], dtype=_F64)
    rgb = light + parity * (dark - light)
    normals = torch.tensor([0.0, 0.0, 1.0], dtype=_F64).expand_as(points)
    return _surfels(points, normals, rgb, spacing)


def _striped_sphere(center: Sequence[float], radius: float, spacing: float) -> dict[str, Tensor]:
    """A red sphere with white latitude stripes."""
    normals = _fibonacci_sphere(max(4, round(4 * math.pi * radius**2 / spacing**2)))
    stripes = (torch.sin(10.0 * torch.asin(normals[:, 2].clamp(-1, 1))) > 0.4).to(_F64)[:, None]
    red, white = torch.tensor([0.85, 0.15, 0.1], dtype=_F64), torch.tensor([0.95, 0.95, 0.95], dtype=_F64)
    rgb = red + stripes * (white - red)
    return _surfels(torch.tensor(center, dtype=_F64) + radius * normals, normals, rgb, spacing)


def _checker_sphere(center: Sequence[float], radius: float, spacing: float) -> dict[str, Tensor]:
    """A sphere with a green/blue longitude-latitude checker pattern."""
    normals = _fibonacci_sphere(max(4, round(4 * math.pi * radius**2 / spacing**2)))
    lon = torch.atan2(normals[:, 1], normals[:, 0])
    lat = torch.asin(normals[:, 2].clamp(-1, 1))
    parity = (torch.floor(lon / (math.pi / 6)) + torch.floor(lat / (math.pi / 6))).remainder(2)[:, None]
    green, blue = torch.tensor([0.2, 0.75, 0.3], dtype=_F64), torch.tensor([0.15, 0.3, 0.85], dtype=_F64)
    rgb = green + parity * (blue - green)
    return _surfels(torch.tensor(center, dtype=_F64) + radius * normals, normals, rgb, spacing)


def _grid_box(center: Sequence[float], half: float, yaw: float, spacing: float) -> dict[str, Tensor]:
    """A cube rotated by ``yaw`` about z, yellow with a dark-blue grid drawn on every face."""
    ticks = torch.arange(-half + spacing / 2, half, spacing, dtype=_F64)
    a, b = torch.meshgrid(ticks, ticks, indexing="ij")
    a, b = a.reshape(-1), b.reshape(-1)
    lines = ((a.remainder(half / 2) < 0.18 * half / 2) | (b.remainder(half / 2) < 0.18 * half / 2)).to(_F64)
    yellow, navy = torch.tensor([0.95, 0.8, 0.2], dtype=_F64), torch.tensor([0.1, 0.1, 0.35], dtype=_F64)
    face_rgb = yellow + lines[:, None] * (navy - yellow)
    points, normals = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = torch.empty(a.shape[0], 3, dtype=_F64)
            p[:, axis] = sign * half
            p[:, (axis + 1) % 3], p[:, (axis + 2) % 3] = a, b
            nrm = torch.zeros_like(p)
            nrm[:, axis] = sign
            points.append(p)
            normals.append(nrm)
    c, s = math.cos(yaw), math.sin(yaw)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=_F64)
    points = torch.cat(points) @ rot.T + torch.tensor(center, dtype=_F64)
    normals = torch.cat(normals) @ rot.T
    return _surfels(points, normals, face_rgb.repeat(6, 1), spacing)


def default_cameras(
    n: int = 24,
    width: int = 256,
    height: int = 256,
    *,
    radius: float = 4.0,
    elevation_deg: float = 30.0,
    fov_x_deg: float = 50.0,
    azimuth_offset_deg: float = 0.0,
) -> list[Camera]:
    """An orbit of cameras around :data:`DEFAULT_SCENE_CENTER` framing the default scene.

    Args:
        n: number of cameras.
        width: image width, pixels.
        height: image height, pixels.
        radius: orbit radius, world units.
        elevation_deg: camera elevation above the ground plane, degrees.
        fov_x_deg: horizontal field of view, degrees.
        azimuth_offset_deg: rotation of the whole orbit (e.g. half a step for held-out views).

    Returns:
        ``n`` cameras (see :func:`gsw.camera.orbit_cameras`).
    """
    return orbit_cameras(
        DEFAULT_SCENE_CENTER, radius, n, width=width, height=height, elevation_deg=elevation_deg,
        fov_x_deg=fov_x_deg, azimuth_offset_deg=azimuth_offset_deg,
    )


def default_scene(
    *,
    sh_degree: int = 3,
    seed: int = 0,
    detail: float = 1.0,
    n_cameras: int = 24,
    width: int = 256,
    height: int = 256,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    sh_rest_std: float = 0.03,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> SyntheticScene:
    """The built-in procedural scene: textured objects on a checkerboard ground, with an orbit of cameras.

    Contents (world z up, ground at ``z = 0``): a 5x5 checkerboard ground (0.5 squares), a red sphere
    with white stripes (radius 0.6 at ``(-0.8, -0.5, 0.6)``), a green/blue checkered sphere (radius 0.45 at
    ``(0.9, -0.3, 0.45)``) and a yellow cube with a navy grid (half size 0.45 at ``(0.1, 1.0, 0.45)``, yawed
    30 degrees). Every surface is covered by flat, nearly opaque Gaussians (discs) on a regular lattice;
    sharp texture edges give the high frequencies watermarking cares about. About 25k Gaussians at
    ``detail = 1``.

    Args:
        sh_degree: SH degree in ``0..3``.
        seed: RNG seed (position jitter, opacities and the small view-dependent ``f_rest`` terms).
        detail: sampling density factor; the Gaussian count grows like ``detail^2``.
        n_cameras: number of orbit cameras (see :func:`default_cameras`).
        width: camera image width, pixels.
        height: camera image height, pixels.
        background: RGB background colour.
        sh_rest_std: standard deviation of the ``f_rest`` coefficients.
        dtype: output dtype.
        device: output device.

    Returns:
        The scene.
    """
    if detail <= 0:
        raise ValueError(f"detail must be positive, got {detail}")
    ground_spacing, object_spacing = 0.05 / detail, 0.03 / detail
    parts = [
        _ground(ground_spacing),
        _striped_sphere((-0.8, -0.5, 0.6), 0.6, object_spacing),
        _checker_sphere((0.9, -0.3, 0.45), 0.45, object_spacing),
        _grid_box((0.1, 1.0, 0.45), 0.45, math.radians(30.0), object_spacing),
    ]
    gen = _generator(seed)
    means = torch.cat([p["means"] for p in parts])
    n = means.shape[0]
    spacings = [ground_spacing] + [object_spacing] * 3
    spacing = torch.cat([torch.full((p["means"].shape[0], 1), s, dtype=_F64) for p, s in zip(parts, spacings)])
    means = means + _normal(gen, (n, 3), 0.05) * spacing
    opacity_logits = torch.logit(_uniform(gen, (n,), 0.9, 0.98))
    rgb = torch.cat([p["rgb"] for p in parts])
    gaussians = _make(
        dict(
            means=means,
            log_scales=torch.cat([p["log_scales"] for p in parts]),
            quats=torch.cat([p["quats"] for p in parts]),
            opacity_logits=opacity_logits,
            sh=_sh_from_rgb(gen, rgb, sh_degree, sh_rest_std),
        ),
        dtype,
        device,
    )
    bg = torch.tensor(list(background), dtype=dtype, device=device)
    if bg.shape != (3,):
        raise ValueError(f"background must be 3 numbers, got {background!r}")
    return SyntheticScene(gaussians, default_cameras(n_cameras, width, height), bg)
