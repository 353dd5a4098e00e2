"""The differentiable rasterizer: autograd wrappers over the compiled C++/CUDA kernels.

:func:`rasterize` renders a :class:`~gsw.gaussians.Gaussians` model from a :class:`~gsw.camera.Camera`;
:func:`contribution` gives each Gaussian's weighted contribution; :func:`rasterization`
(:mod:`gsw.render.functional`) is a drop-in for gsplat's entry point; the kernels are ``torch.library`` custom ops
(:mod:`gsw.render._ops`). :mod:`gsw.render._reference` is the pure-PyTorch oracle the tests compare against.
"""

from __future__ import annotations

from gsw.render.rasterize import (
    ContributionOutput,
    Projection,
    RenderOutput,
    bin_gaussians,
    blend,
    contribution,
    project,
    rasterize,
)
from gsw.render.functional import rasterization

__all__ = ["ContributionOutput", "Projection", "RenderOutput", "bin_gaussians", "blend", "contribution", "project",
           "rasterization", "rasterize"]
