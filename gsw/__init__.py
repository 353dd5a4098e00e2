"""gsw: robust 3D Gaussian Splatting watermarking with its own differentiable rasterizer."""

from __future__ import annotations

__version__ = "0.1.0"
