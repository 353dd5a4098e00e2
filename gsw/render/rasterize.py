"""Differentiable rasterization: thin wrappers over the kernels' custom ops (:mod:`gsw.render._ops`).

Two differentiable stages, as in gsplat:

1. :func:`project` — per-Gaussian EWA projection + SH colour (`means2d`, `conics`, `depths`,
   `colors`, `opacities`, `radii`);
2. :func:`blend` — tile binning and front-to-back alpha blending into an image (one op: the
   data-dependent tile lists stay inside it).

:func:`rasterize` composes them for a :class:`~gsw.gaussians.Gaussians` and a
:class:`~gsw.camera.Camera`; :func:`contribution` computes per-Gaussian blending weights under
a weight map; :func:`gsw.render.functional.rasterization` is the gsplat drop-in. Every stage is a
``torch.library`` custom op, so ``torch.compile(fullgraph=True)`` traces a render and its loss.

Frames: world coordinates for Gaussians; cameras are world-to-camera (OpenCV axes: x right,
y down, z forward); 2-D means are pixels in the `K p` frame, pixel (i, j) has its centre at
(i + 0.5, j + 0.5). Images are channel-major `[3, H, W]`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from gsw._ext import _C
from gsw.device import constant
from gsw.render import _ops

if TYPE_CHECKING:
    from gsw.camera import Camera
    from gsw.gaussians import Gaussians

TileBins = _C.TileBins


def _camera_args(camera: Camera) -> dict[str, Any]:
    return dict(viewmat=camera.viewmat, fx=float(camera.fx), fy=float(camera.fy),
                cx=float(camera.cx), cy=float(camera.cy), width=int(camera.width),
                height=int(camera.height))


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities of one camera.

    Attributes:
        means2d: [N, 2] projected centres in pixels (`K p` frame). Differentiable; call
            `means2d.retain_grad()` before backward to read the screen-space gradient used for
            densification.
        conics: [N, 3] inverse of the dilated 2-D covariance, (a, b, c) of [[a, b], [b, c]].
        depths: [N] view-space z.
        colors: [N, 3] view-dependent RGB.
        opacities: [N] activated opacity.
        radii: [N] int32 screen radius in pixels; 0 means culled. INRIA's 3-sigma radius, or less for
            faint splats: as far as their alpha can reach ALPHA_MIN (about sqrt(2 ln(255 opacity))
            sigmas, plus one pixel); 0 for opacities below ALPHA_MIN. The image does not change.
        nonfinite: optional [1] int32 device flags the projection set for inputs holding NaN/Inf
            (bit k: ``_C.NONFINITE_FIELDS[k]``); :func:`blend` and :func:`bin_gaussians` read them back.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    colors: Tensor
    opacities: Tensor
    radii: Tensor
    nonfinite: Tensor | None = None

    @property
    def visible(self) -> Tensor:
        """[N] bool: Gaussians that touch at least one tile."""
        return self.radii > 0


def project(means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, sh: Tensor,
            camera: Camera, sh_degree: int, *, check_finite: bool = False) -> Projection:
    """Projects Gaussians into a camera (differentiable).

    Args:
        means: [N, 3] world positions.
        quats: [N, 4] rotations (w, x, y, z), unnormalised.
        log_scales: [N, 3] log standard deviations.
        opacity_logits: [N] opacity logits.
        sh: [N, K, 3] SH coefficients, or [N, 3] RGB colours when `sh_degree == -1`.
        camera: the camera.
        sh_degree: active SH degree in 0..3 (uses the first (d+1)^2 coefficients), or -1.
        check_finite: let the projection kernel flag inputs holding NaN/Inf in
            `Projection.nonfinite` (on the device, without synchronising).

    Returns:
        The :class:`Projection`.
    """
    cam = _camera_args(camera)
    radii, means2d, conics, depths, colors, opacities, flags = _ops.call(
        _ops.project, means, quats, log_scales, opacity_logits, sh, int(sh_degree), cam["viewmat"], cam["fx"],
        cam["fy"], cam["cx"], cam["cy"], cam["width"], cam["height"], bool(check_finite))
    return Projection(means2d, conics, depths, colors, opacities, radii, nonfinite=flags if check_finite else None)


def bin_gaussians(proj: Projection, width: int, height: int) -> TileBins:
    """Sorts projected Gaussians into 16x16 tiles, front to back (not differentiable).

    A Gaussian goes to the tiles of its radius rectangle that hold a pixel centre its opacity-aware
    ellipse reaches (where its alpha can reach ALPHA_MIN; `csrc/core/tiles.h`).

    The returned bins' `nonfinite` holds the host copy of `proj.nonfinite` (0 without flags), read
    with the intersection count in the binning's one host synchronisation.
    """
    return _ops.bins(proj.means2d, proj.conics, proj.opacities, proj.radii, proj.depths, width, height,
                     proj.nonfinite)


def _raise_nonfinite(gaussians: Gaussians, colors: Tensor | None, exc: _ops.NonFiniteInputError) -> None:
    """Raises the ValueError naming the fields (and rows) the projection flagged as holding NaN/Inf."""
    names = list(exc.names)
    if colors is not None and "sh" in names:  # the "sh" input was the colour override
        names[names.index("sh")] = "colors (the colour override)"
        raise ValueError("non-finite inputs: " + ", ".join(names) + " contain NaN/Inf")
    gaussians.check_finite()  # names the fields and counts the rows (a host check, on this error path only)
    raise ValueError(str(exc)) from None


def blend(proj: Projection, width: int, height: int,
          background: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Bins and alpha-blends projected Gaussians front to back (differentiable).

    Args:
        proj: the projection; Gaussians with `radii == 0` are left out. `proj.nonfinite` flags (from
            :func:`project` with `check_finite`) are read back with the binning's host synchronisation.
        width: image width.
        height: image height.
        background: [3] RGB composited behind the splats.

    Returns:
        image [3, H, W], alpha [1, H, W], depth [1, H, W] (sum of w_i z_i), final_T [H, W],
        n_contrib [H, W] int32.

    Raises:
        gsw.render._ops.NonFiniteInputError: (a ValueError) the projection flagged NaN/Inf inputs.
    """
    return _blend(proj, width, height, background)[:5]


def _blend(proj: Projection, width: int, height: int, background: Tensor) -> tuple[Tensor, ...]:
    """:func:`blend`'s outputs followed by the bin tensors (see :func:`gsw.render._ops.rasterize`)."""
    return _ops.call(_ops.rasterize, proj.means2d, proj.conics, proj.colors, proj.opacities, proj.depths,
                     background, proj.radii, int(width), int(height), proj.nonfinite)


@dataclass
class RenderOutput:
    """Result of :func:`rasterize`.

    Attributes:
        image: [3, H, W] RGB, background composited.
        alpha: [1, H, W] accumulated opacity.
        depth: [1, H, W] alpha-weighted depth sum (use :attr:`expected_depth` for the mean).
        final_T: [H, W] transmittance left after the last splat.
        n_contrib: [H, W] int32, 1 + index of the last blended splat in the pixel's tile list.
        projection: per-Gaussian screen-space quantities (`means2d` carries the screen-space
            gradient).
        width: image width.
        height: image height.
        bin_tensors: the blending op's bins (tile_offsets, gauss_ids, entry_offsets, entry_slots), see
            :attr:`bins`.
    """

    image: Tensor
    alpha: Tensor
    depth: Tensor
    final_T: Tensor
    n_contrib: Tensor
    projection: Projection
    width: int
    height: int
    bin_tensors: tuple[Tensor, ...]

    @cached_property
    def bins(self) -> TileBins:
        """The render's tile binning (a ``TileBins`` over :attr:`bin_tensors`; `nonfinite` is 0)."""
        return _ops.restore_bins(self.width, self.height, *self.bin_tensors)

    @property
    def radii(self) -> Tensor:
        """[N] int32 pixel radii (0 = culled)."""
        return self.projection.radii

    @property
    def means2d(self) -> Tensor:
        """[N, 2] projected centres in pixels."""
        return self.projection.means2d

    @property
    def visible(self) -> Tensor:
        """[N] bool mask of Gaussians on screen."""
        return self.projection.visible

    def tile_walks(self) -> Tensor:
        """Each tile's walk: the largest :attr:`n_contrib` of its pixels, the splats the blend backward walks there.

        Returns:
            [tiles_y * tiles_x] int64 on the CPU, row-major over the TILE_SIZE x TILE_SIZE tiles (edge tiles
            padded with 0). Their sum is the backward's record count; the largest against that sum is what the
            CUDA backward chooses its layout by (BENCHMARKS.md 2s).
        """
        t = int(_C.constants["TILE_SIZE"])
        H, W = self.height, self.width
        pad = torch.zeros(-(-H // t) * t, -(-W // t) * t, dtype=torch.int64)
        pad[:H, :W] = self.n_contrib.reshape(H, W).cpu()
        return pad.reshape(pad.shape[0] // t, t, pad.shape[1] // t, t).amax(dim=(1, 3)).flatten()

    @property
    def expected_depth(self) -> Tensor:
        """[1, H, W] depth / alpha (0 where nothing was blended)."""
        return torch.where(self.alpha > 0, self.depth / self.alpha.clamp_min(torch.finfo(self.alpha.dtype).tiny),
                           torch.zeros_like(self.depth))


def _background(background: Tensor | tuple[float, float, float] | None, like: Tensor) -> Tensor:
    if isinstance(background, Tensor):
        bg = background.to(dtype=like.dtype, device=like.device)
    else:
        try:
            values = (0.0, 0.0, 0.0) if background is None else tuple(float(v) for v in background)
        except (TypeError, ValueError):
            raise ValueError(f"background must be 3 numbers or a [3] tensor, got {background!r}") from None
        if torch.compiler.is_compiling():  # traced: a constant of the graph
            bg = torch.tensor(values, dtype=like.dtype, device=like.device)
        else:
            bg = constant(values, like.dtype, like.device)  # made once: no synchronisation per render
    if bg.shape != (3,):
        raise ValueError(f"background must have shape [3], got {list(bg.shape)}")
    return bg


def _resolve_sh_degree(gaussians: Gaussians, sh_degree: int | None) -> int:
    if sh_degree is None:
        return gaussians.sh_degree
    if not 0 <= sh_degree <= gaussians.sh_degree:
        raise ValueError(f"sh_degree={sh_degree} is outside 0..{gaussians.sh_degree} "
                         "(the degree stored in the Gaussians)")
    return sh_degree


def rasterize(gaussians: Gaussians, camera: Camera, *, sh_degree: int | None = None,
              background: Tensor | tuple[float, float, float] | None = None,
              colors: Tensor | None = None, validate: bool = True) -> RenderOutput:
    """Renders Gaussians from a camera; differentiable w.r.t. every Gaussian parameter.

    Args:
        gaussians: the scene (world frame).
        camera: world-to-camera pinhole camera (OpenCV axes).
        sh_degree: SH degree to evaluate (default: all stored coefficients).
        background: [3] RGB composited behind the splats (default black).
        colors: optional [N, 3] per-Gaussian RGB that replaces the SH colour (a "colour
            override"; differentiable).
        validate: raise a ValueError naming the field if any parameter (or the colour override)
            is NaN/Inf. The projection kernel flags such values on the device and the flags are read
            back in the binning's host synchronisation, which the render needs anyway: validation
            adds no synchronisation, on the CPU and on CUDA alike.

    Returns:
        A :class:`RenderOutput` with image [3, H, W], alpha, depth and per-Gaussian data.

    Example:
        >>> from gsw.scenes import random_gaussians
        >>> from gsw.camera import Camera
        >>> g = random_gaussians(100, seed=0)
        >>> cam = Camera.look_at((0., -4., 0.), (0., 0., 0.), (0., 0., 1.), 0.8, 64, 48)
        >>> rasterize(g, cam).image.shape
        torch.Size([3, 48, 64])
    """
    if colors is not None:
        n = gaussians.means.shape[0]
        if colors.shape != (n, 3):
            raise ValueError(f"colors must have shape [{n}, 3], got {list(colors.shape)}")
        sh, degree = colors.to(gaussians.means.dtype), -1
    else:
        sh, degree = gaussians.sh, _resolve_sh_degree(gaussians, sh_degree)
    proj = project(gaussians.means, gaussians.quats, gaussians.log_scales,
                   gaussians.opacity_logits, sh, camera, degree, check_finite=validate)
    bg = _background(background, gaussians.means)
    try:
        image, alpha, depth, final_T, n_contrib, *bin_tensors = _blend(proj, camera.width, camera.height, bg)
    except _ops.NonFiniteInputError as exc:
        _raise_nonfinite(gaussians, colors, exc)
    return RenderOutput(image, alpha, depth, final_T, n_contrib, proj, int(camera.width), int(camera.height),
                        tuple(bin_tensors))


@dataclass
class ContributionOutput:
    """Result of :func:`contribution`.

    Attributes:
        values: [N, C] `sum_p weights[c, p] * alpha_i(p) * T_i(p)` (the gradient of
            `sum(weights * image)` w.r.t. a per-Gaussian colour override, for C = 3).
        hits: [N] int32 number of pixels where Gaussian i was blended.
        max_weight: [N] largest blending weight `alpha_i(p) T_i(p)` over pixels.
        radii: [N] int32 pixel radii (0 = culled).
    """

    values: Tensor
    hits: Tensor
    max_weight: Tensor
    radii: Tensor


def contribution_from_projection(proj: Projection, weights: Tensor, width: int, height: int) -> ContributionOutput:
    """Per-Gaussian contribution (see :func:`contribution`) for an already projected view (no gradient)."""
    w = weights.detach().to(proj.means2d.dtype)
    values, hits, max_weight = _ops.call(_ops.contribution, proj.means2d.detach(), proj.conics.detach(),
                                         proj.opacities.detach(), proj.depths.detach(), proj.radii, w, int(width),
                                         int(height))
    return ContributionOutput(values, hits, max_weight, proj.radii)


@torch.no_grad()
def contribution(gaussians: Gaussians, camera: Camera, weights: Tensor) -> ContributionOutput:
    """Per-Gaussian, per-channel contribution of the blending weights under a weight map.

    `V[i, c] = sum_p weights[c, p] * alpha_i(p) * T_i(p)`, computed with the forward traversal
    of the rasterizer (same culling, skipping and early termination).

    Args:
        gaussians: the scene.
        camera: the view.
        weights: [C, H, W] per-pixel weights (any C >= 1), H and W of the camera.

    Returns:
        A :class:`ContributionOutput`.
    """
    if weights.dim() != 3 or tuple(weights.shape[1:]) != (camera.height, camera.width):
        raise ValueError(f"weights must have shape [C, {camera.height}, {camera.width}], "
                         f"got {list(weights.shape)}")
    # Colours play no part in the contribution: the means stand in for the colour override ([N, 3], nothing
    # allocated or filled for it).
    proj = project(gaussians.means, gaussians.quats, gaussians.log_scales,
                   gaussians.opacity_logits, gaussians.means, camera, -1)
    return contribution_from_projection(proj, weights.to(gaussians.means.device), camera.width, camera.height)
