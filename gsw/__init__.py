"""gsw: robust 3D Gaussian Splatting watermarking with its own differentiable rasterizer.

Example:
    >>> import gsw
    >>> from gsw.scenes import default_scene
    >>> scene = default_scene(width=64, height=64)
    >>> out = gsw.rasterize(scene.gaussians, scene.cameras[0], background=scene.background)
    >>> out.image.shape
    torch.Size([3, 64, 64])
"""

from __future__ import annotations

import torch  # noqa: F401  (loads libtorch before the extension)

from gsw import _C
from gsw.camera import Camera, orbit_cameras
from gsw.data import load_dataset, load_inria_model
from gsw.embed import EmbedConfig, EmbedResult, Extraction, Verdict, embed, extract, verify
from gsw.gaussians import Gaussians
from gsw.image_watermark import ImageEmbedConfig, ImageEmbedResult, embed_image, embed_images
from gsw.io import load_gaussians, load_ply, load_splat, save_ply
from gsw.rasterize import (
    ContributionOutput,
    RenderOutput,
    contribution,
    rasterization,
    rasterize,
)

__version__ = "0.1.0"


def build_info() -> dict[str, object]:
    """Describes how the compiled extension was built and how it runs.

    Returns:
        A dict with `version`, `compiler`, `openmp` (bool), `threads` (torch intra-op threads
        used by the CPU kernels), `cuda` (bool: CUDA backend compiled), `cuda_archs`,
        `cuda_available` (a CUDA device is usable now) and `torch` (version).
    """
    info: dict[str, object] = dict(_C.build)
    info.update(version=__version__, threads=torch.get_num_threads(), torch=torch.__version__,
                cuda_available=bool(info["cuda"]) and torch.cuda.is_available())
    return info


__all__ = [
    "Camera", "ContributionOutput", "EmbedConfig", "EmbedResult", "Extraction", "Gaussians",
    "ImageEmbedConfig", "ImageEmbedResult", "RenderOutput", "Verdict", "__version__", "build_info",
    "contribution", "embed", "embed_image", "embed_images", "extract",
    "load_dataset", "load_gaussians", "load_inria_model", "load_ply", "load_splat",
    "orbit_cameras", "rasterization", "rasterize", "save_ply", "verify",
]
