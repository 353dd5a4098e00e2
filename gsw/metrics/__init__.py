"""Image quality metrics: the one PSNR / SSIM (:mod:`gsw.metrics.image`) and LPIPS (:mod:`gsw.metrics.lpips`).

Torch-only: importing this subpackage never loads the compiled rasterizer.
"""

from gsw.metrics.image import mse, psnr, ssim, ssim_loss

__all__ = ["mse", "psnr", "ssim", "ssim_loss"]
