"""gsw: robust 3D Gaussian Splatting watermarking with its own differentiable rasterizer.

The top-level names load lazily: ``import gsw`` is cheap, and the subpackages that do not render
(:mod:`gsw.decoder`, :mod:`gsw.attacks`, :mod:`gsw.metrics`, :mod:`gsw.stats`) work without the
compiled extension.

Layout (one concept per subpackage):
    - scene substrate: :mod:`gsw.gaussians`, :mod:`gsw.camera`, :mod:`gsw.constants`
    - :mod:`gsw.render`: the differentiable rasterizer (autograd over the C++/CUDA kernels)
    - :mod:`gsw.io`, :mod:`gsw.data`, :mod:`gsw.scenes`: file formats, datasets, built-in scenes
    - :mod:`gsw.metrics`: PSNR/SSIM, LPIPS
    - :mod:`gsw.train`: the 3DGS trainer
    - :mod:`gsw.mark`: the 3D-GSW method (message, FGD, mask, loss, embed, detect, 2-D images)
    - :mod:`gsw.decoder`: the frozen watermark decoders (DWT, HiDDeN, whitening, zoo) and their pre-training
    - :mod:`gsw.attacks`: image and model attacks, training noise layers, presets
    - :mod:`gsw.eval`: evaluation report, grid, plots
    - :mod:`gsw.cli`: the ``gsw`` command

Example:
    >>> import gsw
    >>> from gsw.scenes import default_scene
    >>> scene = default_scene(width=64, height=64)
    >>> out = gsw.rasterize(scene.gaussians, scene.cameras[0], background=scene.background)
    >>> out.image.shape
    torch.Size([3, 64, 64])
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: Public name -> module that defines it (imported on first access).
_EXPORTS: dict[str, str] = {
    "Camera": "gsw.camera", "orbit_cameras": "gsw.camera",
    "Gaussians": "gsw.gaussians",
    "load_dataset": "gsw.data", "load_inria_model": "gsw.data",
    "load_gaussians": "gsw.io", "load_ply": "gsw.io", "load_splat": "gsw.io", "save_ply": "gsw.io",
    "ContributionOutput": "gsw.render", "RenderOutput": "gsw.render", "contribution": "gsw.render",
    "rasterization": "gsw.render", "rasterize": "gsw.render",
    "EmbedConfig": "gsw.mark", "EmbedResult": "gsw.mark", "embed": "gsw.mark",
    "Extraction": "gsw.mark", "Verdict": "gsw.mark", "extract": "gsw.mark", "verify": "gsw.mark",
    "ImageEmbedConfig": "gsw.mark", "ImageEmbedResult": "gsw.mark", "embed_image": "gsw.mark",
    "embed_images": "gsw.mark",
    "fingerprint": "gsw.fingerprint",
}


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'gsw' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


def build_info() -> dict[str, object]:
    """Describes how the compiled extension was built and how it runs.

    Returns:
        A dict with `version`, `compiler`, `openmp` (bool), `threads` (torch intra-op threads
        used by the CPU kernels), `cuda` (bool: CUDA backend compiled), `cuda_archs`,
        `cuda_available` (a CUDA device is usable now), `built_with_torch` (the torch version the
        extension was compiled against) and `torch` (the running torch's version).
    """
    import torch

    from gsw._ext import _C

    info: dict[str, object] = dict(_C.build)
    info.update(version=__version__, threads=torch.get_num_threads(), torch=torch.__version__,
                cuda_available=bool(info["cuda"]) and torch.cuda.is_available())
    return info


__all__ = sorted([*_EXPORTS, "__version__", "build_info"])
