"""Deterministic image attacks on renders (evaluation).

This module is an *evaluation* tool, unlike :mod:`gsw.attacks.layers` (random, differentiable noise layers
for decoder training). Every attack here is a plain function with every parameter explicit, and every
random choice is driven by an explicit ``seed`` (a private ``torch.Generator`` on the CPU, so results do not
depend on the global RNG state or on the device). Model attacks live in :mod:`gsw.attacks.model`, the named
tables (the paper's set, the official code's set, robustness sweeps) in :mod:`gsw.attacks.presets`.

All image attacks take a float image ``[3, H, W]`` or a batch ``[B, 3, H, W]`` with values in ``[0, 1]`` and
return a tensor of the same rank, dtype and device with values in ``[0, 1]``. The spatial size is kept,
except where stated:

- :func:`crop` / :func:`official_crop` return the cropped image (smaller ``H, W``),
- :func:`scaling` returns the image at the scaled size unless ``resize_back=True``,
- :func:`combined` returns the cropped size.

The defaults of the attacks are the paper's strengths (3D-GSW, CVPR 2025; ``GUIDE.md`` section 1.7), the one
place these numbers are written (:data:`gsw.attacks.presets.PAPER_IMAGE_ATTACKS` reads them): Gaussian noise
sigma 0.1, rotation pi/6 (30 degrees), scaling to 75 %, Gaussian blur sigma 0.1, crop keeping 40 % of the
area, JPEG quality 50, combined = crop + blur + JPEG. The official code's (mislabelled) settings are kept
under their own names (``official_*``; ``GUIDE.md`` section 2): noise std 0.01, 3x3 blur sigma 0.1, centre
crop keeping 50 % of the area, JPEG quality 10.

Example:
    >>> import torch
    >>> from gsw import attacks
    >>> img = torch.rand(3, 64, 48)
    >>> attacks.crop(img, keep_area=0.4, seed=0).shape
    torch.Size([3, 40, 30])
"""

from __future__ import annotations

import io
import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "gaussian_noise",
    "rotation",
    "scaling",
    "gaussian_blur",
    "gaussian_kernel1d",
    "separable_blur",
    "scaled_size",
    "crop_size",
    "to_uint8",
    "crop",
    "jpeg",
    "combined",
    "brightness",
    "contrast",
    "official_noise",
    "official_blur",
    "official_crop",
    "official_jpeg",
]

# --------------------------------------------------------------------------------------------- helpers


def _round_half_up(x: float) -> int:
    """Round to the nearest integer, ties away from zero for positive ``x`` (``round(2.5) = 3``)."""
    return int(math.floor(x + 0.5))


def _generator(seed: int) -> torch.Generator:
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise TypeError(f"seed must be an int, got {seed!r}")
    return torch.Generator(device="cpu").manual_seed(seed)


def _as_batch(img: Tensor, name: str = "img") -> tuple[Tensor, bool]:
    """Validate ``[3,H,W]`` / ``[B,3,H,W]`` float input; return ``([B,3,H,W], was_single)``."""
    if not isinstance(img, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(img).__name__}")
    if not img.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor in [0, 1], got dtype {img.dtype}")
    if img.dim() == 3 and img.shape[0] == 3:
        return img.unsqueeze(0), True
    if img.dim() == 4 and img.shape[1] == 3:
        return img, False
    raise ValueError(f"{name} must have shape [3, H, W] or [B, 3, H, W], got {list(img.shape)}")


def _restore(x: Tensor, single: bool) -> Tensor:
    return x[0] if single else x


def _check_range(name: str, value: float, lo: float, hi: float, lo_open: bool = False) -> None:
    ok = (lo < value if lo_open else lo <= value) and value <= hi
    if not ok:
        left = "(" if lo_open else "["
        raise ValueError(f"{name} must be in {left}{lo}, {hi}], got {value!r}")


# --------------------------------------------------------------------------------------------- image attacks


def gaussian_noise(img: Tensor, sigma: float = 0.1, seed: int = 0) -> Tensor:
    """Additive white Gaussian noise ``N(0, sigma^2)`` per pixel and channel, then clamp to ``[0, 1]``.

    Paper setting: ``sigma = 0.1`` (in units of the ``[0, 1]`` intensity range).

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        sigma: standard deviation of the noise, ``>= 0``.
        seed: seed of the noise (drawn in float32 on the CPU, so it is device independent).

    Returns:
        Same shape as ``img``, in ``[0, 1]``.
    """
    x, single = _as_batch(img)
    if sigma < 0:
        raise ValueError(f"sigma must be >= 0, got {sigma}")
    noise = torch.randn(x.shape, generator=_generator(seed), dtype=torch.float32)
    out = (x + sigma * noise.to(device=x.device, dtype=x.dtype)).clamp(0.0, 1.0)
    return _restore(out, single)


def rotation(img: Tensor, degrees: float = 30.0) -> Tensor:
    """Rotate about the image centre by ``degrees``, keeping the size; bilinear, black (zero) fill.

    Convention: positive angles rotate the content counter-clockwise as displayed (row 0 at the top), like
    ``torch.rot90(img, 1, dims=(-2, -1))`` for 90 degrees. The rotation is about the centre of the pixel grid
    in pixel units (correct for non-square images); pixels whose source falls outside the image are 0 (black);
    the corners of the original are cut off. Paper setting: pi/6 = 30 degrees (the paper reports +-pi/6;
    use ``-30.0`` for the other direction).

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        degrees: rotation angle in degrees.

    Returns:
        Same shape as ``img``, in ``[0, 1]``.
    """
    x, single = _as_batch(img)
    b, _, h, w = x.shape
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    # Output pixel p (normalised coords, y down) samples the input at R^-1 p, in pixel units.
    theta = torch.tensor([[c, -s * h / w, 0.0], [s * w / h, c, 0.0]], dtype=torch.float64)
    theta = theta.to(device=x.device, dtype=x.dtype).unsqueeze(0).expand(b, 2, 3)
    grid = F.affine_grid(theta, [b, 3, h, w], align_corners=False)
    out = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return _restore(out.clamp(0.0, 1.0), single)


def scaled_size(height: int, width: int, factor: float) -> tuple[int, int]:
    """Size after :func:`scaling`: ``(round(H * factor), round(W * factor))``, rounding half up, at least 1.

    Args:
        height: input height ``H``.
        width: input width ``W``.
        factor: scale factor ``> 0``.

    Returns:
        ``(H', W')``.
    """
    return max(1, _round_half_up(height * factor)), max(1, _round_half_up(width * factor))


def scaling(img: Tensor, factor: float = 0.75, resize_back: bool = False) -> Tensor:
    """Rescale by ``factor`` with bilinear interpolation (antialiased when downscaling).

    Convention: the output is the image at the scaled size ``(round(H*factor), round(W*factor))``
    (see :func:`scaled_size`); this is what a decoder that pools globally sees. With ``resize_back=True`` the
    scaled image is resized back (bilinear) to ``(H, W)``, for decoders that need the original size.
    Paper setting: 75 %.

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        factor: scale factor ``> 0`` (``< 1`` shrinks).
        resize_back: if True, resize the result back to the input size.

    Returns:
        ``[.., 3, H', W']`` (or the input shape with ``resize_back``), in ``[0, 1]``.
    """
    x, single = _as_batch(img)
    if not factor > 0:
        raise ValueError(f"factor must be > 0, got {factor}")
    h, w = x.shape[-2:]
    size = scaled_size(h, w, factor)
    out = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)
    if resize_back and size != (h, w):
        out = F.interpolate(out, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
    return _restore(out.clamp(0.0, 1.0), single)


def gaussian_kernel1d(sigma: float, kernel_size: int | None = None, dtype: torch.dtype = torch.float64) -> Tensor:
    """Normalised 1-D Gaussian kernel.

    Args:
        sigma: standard deviation in pixels, ``> 0``.
        kernel_size: odd size; ``None`` gives ``2 * ceil(3 * sigma) + 1``, at least 3.
        dtype: dtype of the kernel.

    Returns:
        ``[kernel_size]`` weights summing to 1.
    """
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    if kernel_size is None:
        kernel_size = max(3, 2 * math.ceil(3.0 * sigma) + 1)
    if kernel_size < 1 or kernel_size % 2 != 1:
        raise ValueError(f"kernel_size must be a positive odd int, got {kernel_size}")
    r = kernel_size // 2
    t = torch.arange(-r, r + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    return (k / k.sum()).to(dtype)


def separable_blur(x: Tensor, kernel: Tensor) -> Tensor:
    """Convolve every channel with ``kernel`` along the width, then along the height; reflect padding.

    The one blur of the package: :func:`gaussian_blur` and the training layers of :mod:`gsw.attacks.layers`
    call it with a :func:`gaussian_kernel1d`. Differentiable; no clamping.

    Args:
        x: ``[B, C, H, W]``; ``H, W`` must exceed ``kernel.numel() // 2``.
        kernel: ``[K]`` weights, ``K`` odd, in ``x``'s dtype and device.

    Returns:
        ``[B, C, H, W]``.
    """
    r = kernel.numel() // 2
    c = x.shape[1]
    y = F.pad(x, (r, r, r, r), mode="reflect")
    y = F.conv2d(y, kernel.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(y, kernel.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def gaussian_blur(img: Tensor, sigma: float = 0.1, kernel_size: int | None = None) -> Tensor:
    """Separable Gaussian blur with reflect padding (output keeps the size).

    Paper setting: ``sigma = 0.1`` pixel, which with the default kernel (``2*ceil(3 sigma)+1``, at least 3,
    i.e. 3x3) is numerically almost the identity (off-centre weight ``exp(-50) ~ 2e-22``); use
    :func:`gsw.attacks.presets.sweep` for meaningful blur strengths.

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``; ``H, W`` must exceed ``kernel_size // 2``.
        sigma: standard deviation in pixels, ``> 0``.
        kernel_size: odd kernel size; ``None`` gives ``2 * ceil(3 * sigma) + 1``, at least 3.

    Returns:
        Same shape as ``img``, in ``[0, 1]``.
    """
    x, single = _as_batch(img)
    k = gaussian_kernel1d(sigma, kernel_size, dtype=x.dtype).to(x.device)
    return _restore(separable_blur(x, k).clamp(0.0, 1.0), single)


def crop_size(height: int, width: int, keep_area: float) -> tuple[int, int]:
    """Size kept by :func:`crop`: ``(round(H * sqrt(a)), round(W * sqrt(a)))``, rounding half up, at least 1.

    Args:
        height: input height ``H``.
        width: input width ``W``.
        keep_area: fraction ``a`` of the area to keep, in ``(0, 1]``.

    Returns:
        ``(h, w)``.
    """
    _check_range("keep_area", keep_area, 0.0, 1.0, lo_open=True)
    s = math.sqrt(keep_area)
    return max(1, _round_half_up(height * s)), max(1, _round_half_up(width * s))


def crop(img: Tensor, keep_area: float = 0.4, seed: int = 0) -> Tensor:
    """Random crop keeping ``keep_area`` of the area, same aspect ratio; the output is the cropped image.

    Convention: each side is scaled by ``sqrt(keep_area)`` (see :func:`crop_size`), the top-left corner is
    uniform over all valid integer positions, drawn independently per image of a batch (in batch order) from
    one generator seeded with ``seed``. Nothing is resized or padded back. Paper setting: 40 % of the area.

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        keep_area: fraction of the area kept, in ``(0, 1]``.
        seed: seed of the crop positions.

    Returns:
        ``[.., 3, h, w]`` with ``(h, w) = crop_size(H, W, keep_area)``.
    """
    x, single = _as_batch(img)
    h0, w0 = x.shape[-2:]
    h, w = crop_size(h0, w0, keep_area)
    gen = _generator(seed)
    outs = []
    for i in range(x.shape[0]):
        top = int(torch.randint(0, h0 - h + 1, (1,), generator=gen))
        left = int(torch.randint(0, w0 - w + 1, (1,), generator=gen))
        outs.append(x[i, :, top : top + h, left : left + w])
    return _restore(torch.stack(outs).clone(), single)


def _pil_jpeg_u8(arr: np.ndarray, quality: int, subsampling: str) -> np.ndarray:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(arr, mode="RGB").save(buf, format="JPEG", quality=quality, subsampling=subsampling)
    buf.seek(0)
    with Image.open(buf) as im:
        return np.asarray(im.convert("RGB")).copy()


def to_uint8(img: Tensor) -> Tensor:
    """Quantise a ``[0, 1]`` float image to ``uint8``: ``round(clamp(x, 0, 1) * 255)``.

    Args:
        img: float tensor of any shape.

    Returns:
        ``uint8`` tensor of the same shape.
    """
    return (img.detach().clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)


@torch.no_grad()
def jpeg(img: Tensor, quality: int = 50, subsampling: str = "4:2:0") -> Tensor:
    """Real JPEG round trip through Pillow (libjpeg), not differentiable.

    The image is quantised with :func:`to_uint8`, encoded with ``PIL.Image.save(format="JPEG",
    quality=quality, subsampling=subsampling)``, decoded by Pillow and divided by 255; the result equals
    Pillow's own round trip exactly in the ``uint8`` domain. Paper setting: quality 50.

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        quality: JPEG quality in ``1..100``.
        subsampling: chroma subsampling, ``"4:2:0"`` (default), ``"4:2:2"`` or ``"4:4:4"``.

    Returns:
        Same shape as ``img``, multiples of 1/255 in ``[0, 1]``.
    """
    x, single = _as_batch(img)
    if not isinstance(quality, int) or isinstance(quality, bool) or not 1 <= quality <= 100:
        raise ValueError(f"quality must be an int in 1..100, got {quality!r}")
    if subsampling not in ("4:2:0", "4:2:2", "4:4:4"):
        raise ValueError(f"subsampling must be '4:2:0', '4:2:2' or '4:4:4', got {subsampling!r}")
    u8 = to_uint8(x).permute(0, 2, 3, 1).cpu().numpy()
    out = np.stack([_pil_jpeg_u8(np.ascontiguousarray(a), quality, subsampling) for a in u8])
    y = torch.from_numpy(out).permute(0, 3, 1, 2).to(device=x.device, dtype=x.dtype) / 255.0
    return _restore(y, single)


def combined(
    img: Tensor,
    keep_area: float = 0.4,
    blur_sigma: float = 0.1,
    quality: int = 50,
    seed: int = 0,
) -> Tensor:
    """Paper's combined attack: :func:`crop` then :func:`gaussian_blur` then :func:`jpeg`.

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        keep_area: crop's area fraction, in ``(0, 1]``.
        blur_sigma: blur's sigma in pixels (default kernel size).
        quality: JPEG quality in ``1..100`` (4:2:0).
        seed: seed of the crop position.

    Returns:
        The cropped size ``[.., 3, h, w]`` (see :func:`crop_size`), in ``[0, 1]``.
    """
    return jpeg(gaussian_blur(crop(img, keep_area=keep_area, seed=seed), sigma=blur_sigma), quality=quality)


def brightness(img: Tensor, factor: float = 1.5) -> Tensor:
    """Multiply every pixel by ``factor`` and clamp to ``[0, 1]`` (torchvision's ``adjust_brightness``).

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        factor: ``>= 0``; 1 is the identity, 0 gives black.

    Returns:
        Same shape as ``img``, in ``[0, 1]``.
    """
    x, single = _as_batch(img)
    if factor < 0:
        raise ValueError(f"factor must be >= 0, got {factor}")
    return _restore((x * factor).clamp(0.0, 1.0), single)


def contrast(img: Tensor, factor: float = 1.5) -> Tensor:
    """Blend each image with its mean grey level (torchvision's ``adjust_contrast``), clamp to ``[0, 1]``.

    ``out = m + factor * (img - m)`` with ``m`` the per-image mean of the luma
    ``0.299 R + 0.587 G + 0.114 B``.

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        factor: ``>= 0``; 1 is the identity, 0 gives a uniform grey image.

    Returns:
        Same shape as ``img``, in ``[0, 1]``.
    """
    x, single = _as_batch(img)
    if factor < 0:
        raise ValueError(f"factor must be >= 0, got {factor}")
    wts = torch.tensor([0.299, 0.587, 0.114], dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    m = (x * wts).sum(dim=1, keepdim=True).mean(dim=(-2, -1), keepdim=True)
    return _restore((m + factor * (x - m)).clamp(0.0, 1.0), single)


# ----------------------------------------------------------------- the official code's variants


def official_noise(img: Tensor, std: float = 0.01, seed: int = 0) -> Tensor:
    """Official code's "sigma 0.1" noise, which is really std 0.01: :func:`gaussian_noise` with ``std``.

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        std: noise standard deviation.
        seed: noise seed.

    Returns:
        Same shape as ``img``, in ``[0, 1]``.
    """
    return gaussian_noise(img, sigma=std, seed=seed)


def official_blur(img: Tensor, kernel_size: int = 3, sigma: float = 0.1) -> Tensor:
    """Official code's blur: 3x3 kernel, sigma 0.1 (:func:`gaussian_blur`).

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        kernel_size: odd kernel size.
        sigma: sigma in pixels.

    Returns:
        Same shape as ``img``, in ``[0, 1]``.
    """
    return gaussian_blur(img, sigma=sigma, kernel_size=kernel_size)


def official_crop(img: Tensor, keep_area: float = 0.5) -> Tensor:
    """Official code's crop: a deterministic centre crop keeping 50 % of the area, same aspect ratio.

    The size is :func:`crop_size`; the offset is ``(H - h) // 2, (W - w) // 2``. Output is the cropped image.

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        keep_area: fraction of the area kept, in ``(0, 1]``.

    Returns:
        ``[.., 3, h, w]``.
    """
    x, single = _as_batch(img)
    h0, w0 = x.shape[-2:]
    h, w = crop_size(h0, w0, keep_area)
    top, left = (h0 - h) // 2, (w0 - w) // 2
    return _restore(x[..., top : top + h, left : left + w].clone(), single)


def official_jpeg(img: Tensor, quality: int = 10) -> Tensor:
    """Official code's JPEG: quality 10 (:func:`jpeg`, 4:2:0).

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``.
        quality: JPEG quality in ``1..100``.

    Returns:
        Same shape as ``img``.
    """
    return jpeg(img, quality=quality)

