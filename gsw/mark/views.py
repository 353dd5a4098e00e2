"""Viewpoints beyond the given cameras, for embedding a watermark that every view of a 3DGS carries.

A 3DGS can be rendered from anywhere, at any size; a mark fine-tuned on a handful of cameras learns
per-view patterns and does not reach new viewpoints. :class:`ViewSampler` draws training cameras around
the scene's *content* (:func:`content_bounds`: centre and radius from the opacity-weighted Gaussian means,
robust to stray Gaussians far away):

* ``jitter``: a given camera moved on a sphere around the content centre by up to ``jitter_deg`` degrees,
  its distance scaled by up to +-20 %;
* ``interpolate``: a pose between two given cameras (directions from the centre slerped, distances and
  up vectors interpolated);
* ``between``: as ``interpolate``, between a given camera and its nearest neighbour (the given camera whose
  direction from the centre is closest), at a fraction in [0.25, 0.75] of the way: the gaps between the views,
  where a mark fine-tuned on the given cameras is weakest;
* ``orbit``: a direction on the sphere around the content at an elevation in ``elevation_deg`` (relative
  to the cameras' mean up vector, or world +z with no cameras), at a distance between the given cameras'
  nearest and farthest (with no cameras: the distance at which the content sphere fills the view, times
  ``distance_range``).

Every sampled camera looks at the content centre (plus an offset of at most ``target_jitter`` x radius),
stays outside the content sphere, and gets a focal length scaled by a log-uniform factor in
``focal_range`` and an image ``size_range`` x the base size (the given cameras' size, or ``base_size``).
:func:`scale_camera` renders the same view at another size (a render-size change), cropped to at most
``max_side`` pixels per side so that large scales stay cheap. Deterministic under a seed.

Example:
    >>> import torch
    >>> from gsw.gaussians import Gaussians
    >>> g = Gaussians(torch.randn(500, 3), torch.full((500, 3), -3.0), torch.tensor([[1.0, 0, 0, 0]]).repeat(500, 1),
    ...               torch.zeros(500), torch.zeros(500, 1, 3))
    >>> cams = ViewSampler(g, seed=0).sample_many(4)
    >>> len(cams), cams[0].width
    (4, 512)
"""

from __future__ import annotations

import copy
import math
import random
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from gsw.camera import MAX_IMAGE_SIZE, Camera
from gsw.gaussians import Gaussians

__all__ = ["ViewSamplerConfig", "ViewSampler", "content_bounds", "gap_views", "scale_camera", "MODES"]

#: Sampling modes of :class:`ViewSampler` (``jitter``, ``interpolate`` and ``between`` need given cameras).
MODES: tuple[str, ...] = ("jitter", "interpolate", "between", "orbit")
_F64 = torch.float64


def content_bounds(gaussians: Gaussians, quantile: float = 0.9) -> tuple[Tensor, float]:
    """Centre and radius of a model's content, robust to outliers.

    The centre is the per-axis opacity-weighted median of the Gaussian means; the radius is the
    opacity-weighted ``quantile`` of the distances from it. A few far, faint or floating Gaussians (a
    background sky sphere, stray splats) barely move either.

    Args:
        gaussians: the model (at least one Gaussian).
        quantile: share of the opacity mass inside the radius, in (0, 1].

    Returns:
        ``(centre [3] float64 CPU, radius > 0)``.
    """
    if len(gaussians) == 0:
        raise ValueError("content_bounds needs at least one Gaussian")
    if not 0.0 < quantile <= 1.0:
        raise ValueError(f"quantile must be in (0, 1], got {quantile}")
    means = gaussians.means.detach().to("cpu", _F64)
    w = gaussians.opacities.detach().to("cpu", _F64).clamp_min(1e-12)
    finite = torch.isfinite(means).all(1) & torch.isfinite(w)
    if not finite.any():
        raise ValueError("content_bounds: no Gaussian has a finite position and opacity")
    means, w = means[finite], w[finite]
    centre = torch.stack([_weighted_quantile(means[:, j], w, 0.5) for j in range(3)])
    radius = float(_weighted_quantile((means - centre).norm(dim=1), w, quantile))
    return centre, max(radius, 1e-6)


def _weighted_quantile(x: Tensor, w: Tensor, q: float) -> Tensor:
    order = torch.argsort(x)
    cdf = torch.cumsum(w[order], 0)
    i = int(torch.searchsorted(cdf, q * cdf[-1]).clamp_max(len(x) - 1))
    return x[order][i]


def scale_camera(camera: Camera, scale: float, max_side: int | None = None, rng: random.Random | None = None,
                 name: str | None = None) -> Camera:
    """The same view rendered ``scale`` times larger (or smaller), cropped to at most ``max_side`` pixels.

    Focal lengths and the principal point scale with the image (a render-size change, as
    :meth:`gsw.camera.Camera.scaled`); when a side would exceed ``max_side`` a random window of that size
    (``rng``; centred without one) is kept, which renders exactly that window of the large image.

    Args:
        camera: the view.
        scale: size factor, > 0.
        max_side: largest width / height of the result, or None for no crop.
        rng: window position.
        name: label of the result (default: the camera's).

    Returns:
        A new camera with the same pose.
    """
    cam = camera.scaled(scale) if scale != 1.0 else camera
    width, height, cx, cy = cam.width, cam.height, cam.cx, cam.cy
    if max_side is not None and max(width, height) > max_side:
        new_w, new_h = min(width, max_side), min(height, max_side)
        ox = (width - new_w) * (rng.random() if rng else 0.5)
        oy = (height - new_h) * (rng.random() if rng else 0.5)
        ox, oy = float(round(ox)), float(round(oy))
        width, height, cx, cy = new_w, new_h, cx - ox, cy - oy
    return Camera(viewmat=cam.viewmat, fx=cam.fx, fy=cam.fy, cx=cx, cy=cy, width=width, height=height,
                  name=camera.name if name is None else name)


@dataclass(frozen=True)
class ViewSamplerConfig:
    """Ranges of :class:`ViewSampler`.

    Attributes:
        modes: mode -> relative weight (modes needing given cameras are skipped without them).
        jitter_deg: largest angle (degrees, around the content centre) a jittered camera moves.
        elevation_deg: ``(lowest, highest)`` orbit elevation, degrees, relative to the up vector.
        distance_range: orbit distance factors: with cameras, of ``(nearest, farthest)`` camera distance;
            without, of the distance at which the content sphere just fills the narrower field of view.
        focal_range: ``(smallest, largest)`` focal-length factor (log-uniform; > 1 zooms in).
        size_range: ``(smallest, largest)`` image-size factor of the base size (log-uniform).
        base_size: image side without cameras, pixels.
        fov_deg: horizontal field of view without cameras, degrees.
        max_side: largest rendered side, pixels (larger images are cropped, :func:`scale_camera`).
        target_jitter: largest offset of the look-at point from the content centre, in content radii.
        quantile: opacity mass inside the content radius (:func:`content_bounds`).
    """

    modes: tuple[tuple[str, float], ...] = (("jitter", 1.0), ("interpolate", 1.0), ("orbit", 1.0))
    jitter_deg: float = 15.0
    elevation_deg: tuple[float, float] = (-20.0, 80.0)
    distance_range: tuple[float, float] = (0.85, 1.3)
    focal_range: tuple[float, float] = (0.8, 1.25)
    size_range: tuple[float, float] = (0.5, 1.5)
    base_size: int = 512
    fov_deg: float = 50.0
    max_side: int = 1024
    target_jitter: float = 0.15
    quantile: float = 0.9

    def __post_init__(self) -> None:
        unknown = [m for m, _ in self.modes if m not in MODES]
        if unknown or not self.modes or any(w < 0 for _, w in self.modes) or sum(w for _, w in self.modes) <= 0:
            raise ValueError(f"ViewSamplerConfig.modes: (mode, weight >= 0) pairs of {MODES} with a positive "
                             f"total, got {self.modes}")
        for name in ("distance_range", "focal_range", "size_range"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"ViewSamplerConfig.{name} must satisfy 0 < low <= high, got {(lo, hi)}")
        lo, hi = self.elevation_deg
        if not -90.0 < lo <= hi < 90.0:
            raise ValueError(f"ViewSamplerConfig.elevation_deg must be within (-90, 90), got {(lo, hi)}")
        if not 0.0 <= self.jitter_deg <= 180.0 or not 0.0 < self.fov_deg < 180.0:
            raise ValueError("ViewSamplerConfig: jitter_deg must be in [0, 180] and fov_deg in (0, 180)")
        if not 1 <= self.base_size <= MAX_IMAGE_SIZE or not 16 <= self.max_side <= MAX_IMAGE_SIZE:
            raise ValueError(f"ViewSamplerConfig: base_size in 1..{MAX_IMAGE_SIZE}, max_side in 16..{MAX_IMAGE_SIZE}")
        if not 0.0 <= self.target_jitter < 1.0:
            raise ValueError(f"ViewSamplerConfig.target_jitter must be in [0, 1), got {self.target_jitter}")


class ViewSampler:
    """Draws cameras around a model's content (see the module docstring).

    Args:
        gaussians: the model (only its means and opacities are read, once).
        cameras: its given views, or None (bare model: orbit views only).
        config: the ranges.
        seed: RNG seed; the same seed gives the same sequence of cameras.
    """

    def __init__(self, gaussians: Gaussians, cameras: Sequence[Camera] | None = None,
                 config: ViewSamplerConfig | None = None, seed: int = 0) -> None:
        self.config = config or ViewSamplerConfig()
        self.cameras = list(cameras or [])
        self.centre, self.radius = content_bounds(gaussians, self.config.quantile)
        self.rng = random.Random(seed)
        needed = {"orbit": 0, "jitter": 1, "interpolate": 2, "between": 2}  # given cameras each mode needs
        modes = [(m, w) for m, w in self.config.modes if w > 0 and len(self.cameras) >= needed[m]]
        if not modes:
            modes = [("orbit", 1.0)]
        self._modes, self._weights = [m for m, _ in modes], [w for _, w in modes]
        if self.cameras:
            ups = torch.stack([-c.c2w[:3, 1].detach().to("cpu", _F64) for c in self.cameras]).mean(0)
            self.up = ups / ups.norm() if ups.norm() > 1e-6 else torch.tensor([0.0, 0.0, 1.0], dtype=_F64)
            offsets = torch.stack([c.center.detach().to("cpu", _F64) - self.centre for c in self.cameras])
            d = offsets.norm(dim=1)
            self.distances = (float(d.min()), float(d.max()))
            dirs = offsets / d.clamp_min(1e-12)[:, None]
            # per camera, the other one whose direction from the centre is closest (mode "between")
            self._nearest = (dirs @ dirs.T).fill_diagonal_(-math.inf).argmax(dim=1).tolist()
        else:
            self.up = torch.tensor([0.0, 0.0, 1.0], dtype=_F64)
            half = math.radians(self.config.fov_deg) / 2
            self.distances = (self.radius / math.sin(half),) * 2

    def sample(self) -> Camera:
        """One camera."""
        mode = self.rng.choices(self._modes, self._weights)[0]
        cfg = self.config
        if mode == "jitter":
            base = self.rng.choice(self.cameras)
            offset = base.center.detach().to("cpu", _F64) - self.centre
            direction = _rotate_random(offset / offset.norm(), math.radians(cfg.jitter_deg), self.rng)
            distance = float(offset.norm()) * math.exp(self.rng.uniform(math.log(0.8), math.log(1.2)))
            up = -base.c2w[:3, 1].detach().to("cpu", _F64)
        elif mode in ("interpolate", "between"):
            if mode == "interpolate":
                a, b = self.rng.sample(self.cameras, 2)
                t = self.rng.random()
            else:
                i = self.rng.randrange(len(self.cameras))
                a, b = self.cameras[i], self.cameras[self._nearest[i]]
                t = self.rng.uniform(0.25, 0.75)
            oa, ob = (c.center.detach().to("cpu", _F64) - self.centre for c in (a, b))
            direction = _slerp(oa / oa.norm(), ob / ob.norm(), t)
            distance = (1 - t) * float(oa.norm()) + t * float(ob.norm())
            up = -((1 - t) * a.c2w[:3, 1] + t * b.c2w[:3, 1]).detach().to("cpu", _F64)
            base = a if t < 0.5 else b
        else:
            direction = self._orbit_direction()
            near, far = self.distances
            distance = self.rng.uniform(near * cfg.distance_range[0], far * cfg.distance_range[1])
            up, base = self.up, (self.rng.choice(self.cameras) if self.cameras else None)
        distance = max(distance, 1.05 * self.radius)
        return self._camera(direction, distance, up, base, mode)

    def reseeded(self, seed: int) -> ViewSampler:
        """This sampler (the same content bounds and cameras, computed once) drawing its own sequence from
        ``seed``: what ``ViewSampler(gaussians, cameras, config, seed)`` would draw."""
        other = copy.copy(self)
        other.rng = random.Random(seed)
        return other

    def sample_many(self, n: int) -> list[Camera]:
        """``n`` cameras (the next ``n`` of the sequence)."""
        return [self.sample() for _ in range(n)]

    def _orbit_direction(self) -> Tensor:
        lo, hi = (math.radians(v) for v in self.config.elevation_deg)
        el = math.asin(self.rng.uniform(math.sin(lo), math.sin(hi)))  # uniform on the sphere's zone
        az = self.rng.uniform(0.0, 2 * math.pi)
        e1, e2 = _basis(self.up)
        return math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * self.up

    def _camera(self, direction: Tensor, distance: float, up: Tensor, base: Camera | None, mode: str) -> Camera:
        cfg = self.config
        eye = self.centre + distance * direction
        offset = torch.tensor([self.rng.gauss(0.0, 1.0) for _ in range(3)], dtype=_F64)
        target = self.centre + offset / offset.norm().clamp_min(1e-12) * self.rng.random() * cfg.target_jitter * self.radius
        if base is not None:
            width, height, fov_x = base.width, base.height, base.fov_x
        else:
            width = height = cfg.base_size
            fov_x = math.radians(cfg.fov_deg)
        forward = (target - eye) / (target - eye).norm()
        if float(torch.linalg.cross(forward, up).norm()) < 1e-3 * float(up.norm()):
            up = _basis(forward)[0]  # looking along the up vector: any perpendicular up
        zoom = math.exp(self.rng.uniform(*(math.log(v) for v in cfg.focal_range)))
        fov_x = 2 * math.atan(math.tan(fov_x / 2) / zoom)
        cam = Camera.look_at(eye, target, up, fov_x, width, height, name=f"sampled_{mode}")
        size = math.exp(self.rng.uniform(*(math.log(v) for v in cfg.size_range)))
        return scale_camera(cam, size, cfg.max_side, self.rng)


def gap_views(gaussians: Gaussians, cameras: Sequence[Camera], n: int, seed: int = 0,
              max_side: int = MAX_IMAGE_SIZE) -> list[Camera]:
    """``n`` viewpoints in the gaps between neighbouring given cameras (:class:`ViewSampler`'s ``between`` mode),
    at their focal length and image size (at most ``max_side`` per side), looking at the content centre.

    Args:
        gaussians: the model (its content bounds).
        cameras: its given views (at least 2).
        n: how many.
        seed: RNG seed (the same seed, the same viewpoints).
        max_side: largest rendered side, pixels.

    Raises:
        ValueError: fewer than 2 cameras.
    """
    if len(cameras) < 2:
        raise ValueError(f"gap_views needs at least 2 given cameras to look between, got {len(cameras)}")
    cfg = ViewSamplerConfig(modes=(("between", 1.0),), focal_range=(1.0, 1.0), size_range=(1.0, 1.0),
                            target_jitter=0.0, max_side=max_side)
    return ViewSampler(gaussians, cameras, cfg, seed).sample_many(n)


def _basis(up: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors orthogonal to ``up`` and to each other."""
    u = up / up.norm()
    axis = torch.eye(3, dtype=_F64)[0 if abs(float(u[0])) < 0.9 else 1]
    e1 = axis - (axis @ u) * u
    e1 = e1 / e1.norm()
    return e1, torch.linalg.cross(u, e1)


def _rotate_random(v: Tensor, max_angle: float, rng: random.Random) -> Tensor:
    """``v`` (unit) tilted by an angle uniform in [0, max_angle] towards a random perpendicular direction."""
    e1, e2 = _basis(v)
    phi, angle = rng.uniform(0.0, 2 * math.pi), rng.uniform(0.0, max_angle)
    return math.cos(angle) * v + math.sin(angle) * (math.cos(phi) * e1 + math.sin(phi) * e2)


def _slerp(a: Tensor, b: Tensor, t: float) -> Tensor:
    """Spherical interpolation between unit vectors (linear, renormalised, when nearly parallel or opposite)."""
    cos = float((a @ b).clamp(-1.0, 1.0))
    omega = math.acos(cos)
    if math.sin(omega) < 1e-6:
        v = (1 - t) * a + t * b
        return v / v.norm() if v.norm() > 1e-9 else _basis(a)[0]
    return (math.sin((1 - t) * omega) * a + math.sin(t * omega) * b) / math.sin(omega)
