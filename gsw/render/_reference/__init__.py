"""Dense, slow, pure-PyTorch reference rasterizer (differentiable by autograd).

This package re-implements, operation by operation, the semantics of the C++ kernels whose math
lives in ``csrc/core/math.h`` (thresholds in ``csrc/core/constants.h``, data layout in
``csrc/core/params.h``). It exists to test those kernels: forward outputs should agree to
about 1e-5 in float32 and gradients obtained by ``torch.autograd`` through this package are the
ground truth for the hand-written backward passes.

Two stages, one module each, and the tile assignment:
  * :mod:`~gsw.render._reference.project`: 3-D Gaussians -> 2-D splats (:func:`reference_project`,
    the SH basis, tile rectangles);
  * :mod:`~gsw.render._reference.tiles`: the tiles each splat is binned to (:func:`reference_tile_spans`,
    ``csrc/core/tiles.h``), which define each tile's list (and so ``n_contrib``);
  * :mod:`~gsw.render._reference.blend`: 2-D splats -> image (:func:`reference_rasterize_projected`,
    :func:`reference_contribution`) and both stages together (:func:`reference_rasterize`).

Design choices:
  * No tiling, sorting by tile or early-out tricks: every (Gaussian, pixel) pair is evaluated
    densely and the discrete rules (culling, tile membership, alpha thresholds, termination)
    are applied as boolean masks. Masks are computed from values and are never differentiated;
    the differentiable values go through ``torch.where`` so masked branches get exactly zero
    gradient, and every masked branch is fed "safe" inputs so that no NaN/inf can leak into the
    gradient.
  * Transmittance is propagated by an explicit front-to-back loop over the depth-sorted
    Gaussians, each step vectorised over all pixels. This reproduces the C++ sequence of
    float operations ``T <- T * (1 - alpha)`` exactly (``torch.cumprod`` accumulates float32 in
    double on CPU and would make the termination test disagree at the boundary).
  * Every threshold is imported from :mod:`gsw.constants` and cast to the working dtype
    first, like ``T(CONSTANT)`` in the C++ templates. Floating-point expressions are written
    in the same association order as ``math.h``.
  * Work is done in the dtype of ``means`` (float32 or float64). Memory is O(N * P) for N
    Gaussians and P pixels (kept for autograd anyway); ``pixel_chunk`` bounds the size of the
    temporary [N, P] tensors of one chunk.

Frames:
  * world: the frame of ``means``;
  * camera: ``p_cam = R p + t`` with ``viewmat = [[R, t], [0, 1]]`` world-to-camera, OpenCV
    axes (x right, y down, z forward);
  * image: ``mean2d = (fx x/z + cx, fy y/z + cy)`` in pixels; pixel (i, j) (column i, row j)
    has its centre at (i + 0.5, j + 0.5) in this frame.

Example:
    >>> import torch
    >>> from gsw.render._reference import reference_rasterize
    >>> out = reference_rasterize(
    ...     torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
    ...     torch.full((1, 3), -2.0), torch.zeros(1), torch.ones(1, 3), torch.eye(4),
    ...     20.0, 20.0, 8.5, 8.5, 16, 16, -1, torch.zeros(3))
    >>> out.image.shape
    torch.Size([3, 16, 16])
"""

from gsw.render._reference.blend import (ReferenceRender, reference_contribution, reference_rasterize,
                                         reference_rasterize_projected)
from gsw.render._reference.project import (ReferenceProjection, reference_project, reference_sh_basis,
                                           reference_tile_rects)
from gsw.render._reference.tiles import reference_tile_spans

__all__ = [
    "ReferenceProjection",
    "ReferenceRender",
    "reference_sh_basis",
    "reference_tile_rects",
    "reference_tile_spans",
    "reference_project",
    "reference_rasterize_projected",
    "reference_rasterize",
    "reference_contribution",
]
