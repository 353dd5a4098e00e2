"""Evaluation attacks: image attacks on renders and model attacks on :class:`~gsw.gaussians.Gaussians`.

This module is an *evaluation* tool, unlike :mod:`gsw.attacks.layers` (random, differentiable noise layers
for decoder training). Every attack here is a plain function with every parameter explicit, and every
random choice is driven by an explicit ``seed`` (a private ``torch.Generator`` on the CPU, so results do not
depend on the global RNG state or on the device).

Image attacks
-------------
All image attacks take a float image ``[3, H, W]`` or a batch ``[B, 3, H, W]`` with values in ``[0, 1]`` and
return a tensor of the same rank, dtype and device with values in ``[0, 1]``. The spatial size is kept,
except where stated:

- :func:`crop` / :func:`official_crop` return the cropped image (smaller ``H, W``),
- :func:`scaling` returns the image at the scaled size unless ``resize_back=True``,
- :func:`combined` returns the cropped size.

The paper's table (3D-GSW, CVPR 2025; ``GUIDE.md`` section 1.7) is implemented with the defaults:
Gaussian noise sigma 0.1, rotation pi/6 (30 degrees), scaling to 75 %, Gaussian blur sigma 0.1, crop keeping
40 % of the area, JPEG quality 50, combined = crop + blur + JPEG. The official code's (mislabelled)
settings are kept under their own names (``official_*``; ``GUIDE.md`` section 2): noise std 0.01, 3x3 blur
sigma 0.1, centre crop keeping 50 % of the area, JPEG quality 10.

Model attacks
-------------
Model attacks take a :class:`Gaussians` and return new Gaussians whose tensors never alias the input's;
the input is never modified. :data:`MODEL_ATTACKS` need nothing else; :data:`VIEW_MODEL_ATTACKS`
(:func:`finetune`) also render the model from given cameras, and :func:`bind_model_attacks` binds them
to a scene's views.

Example:
    >>> import torch
    >>> from gsw import attacks
    >>> img = torch.rand(3, 64, 48)
    >>> attacks.crop(img, keep_area=0.4, seed=0).shape
    torch.Size([3, 40, 30])
    >>> sorted(attacks.IMAGE_ATTACKS)
    ['blur', 'brightness', 'combined', 'contrast', 'crop', 'jpeg', 'noise', 'rotation', 'scaling']
"""

from __future__ import annotations

import functools
import io
import math
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from gsw.gaussians import Gaussians, cat_gaussians

if TYPE_CHECKING:
    from gsw.camera import Camera

__all__ = [
    "gaussian_noise",
    "rotation",
    "scaling",
    "gaussian_blur",
    "gaussian_kernel1d",
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
    "IMAGE_ATTACKS",
    "OFFICIAL_ATTACKS",
    "SWEEPS",
    "sweep",
    "sweep_parameter",
    "MODEL_FIELDS",
    "finetune",
    "VIEW_MODEL_ATTACKS",
    "MODEL_ATTACK_NAMES",
    "bind_model_attacks",
    "parameter_noise",
    "parameter_noise_attributes",
    "remove_random",
    "clone_random",
    "reduce_sh",
    "prune_by_opacity",
    "quantize",
    "MODEL_ATTACKS",
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


def gaussian_blur(img: Tensor, sigma: float = 0.1, kernel_size: int | None = None) -> Tensor:
    """Separable Gaussian blur with reflect padding (output keeps the size).

    Paper setting: ``sigma = 0.1`` pixel, which with the default kernel (``2*ceil(3 sigma)+1``, at least 3,
    i.e. 3x3) is numerically almost the identity (off-centre weight ``exp(-50) ~ 2e-22``); use
    :func:`sweep` for meaningful blur strengths.

    Args:
        img: ``[3, H, W]`` or ``[B, 3, H, W]`` in ``[0, 1]``; ``H, W`` must exceed ``kernel_size // 2``.
        sigma: standard deviation in pixels, ``> 0``.
        kernel_size: odd kernel size; ``None`` gives ``2 * ceil(3 * sigma) + 1``, at least 3.

    Returns:
        Same shape as ``img``, in ``[0, 1]``.
    """
    x, single = _as_batch(img)
    k = gaussian_kernel1d(sigma, kernel_size, dtype=x.dtype).to(x.device)
    r = k.numel() // 2
    b, c, h, w = x.shape
    y = x.reshape(b * c, 1, h, w)
    y = F.pad(y, (r, r, r, r), mode="reflect")
    y = F.conv2d(y, k.view(1, 1, 1, -1))
    y = F.conv2d(y, k.view(1, 1, -1, 1))
    return _restore(y.reshape(b, c, h, w).clamp(0.0, 1.0), single)


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


#: The paper's fixed-strength image attacks (defaults of each function), plus brightness and contrast (factor
#: 1.5, as in Stable Signature's evaluation); call as ``fn(img)``.
IMAGE_ATTACKS: dict[str, Callable[[Tensor], Tensor]] = {
    "noise": gaussian_noise,
    "rotation": rotation,
    "scaling": scaling,
    "blur": gaussian_blur,
    "crop": crop,
    "jpeg": jpeg,
    "combined": combined,
    "brightness": brightness,
    "contrast": contrast,
}

#: The official code's attack settings (not the paper's); call as ``fn(img)``.
OFFICIAL_ATTACKS: dict[str, Callable[[Tensor], Tensor]] = {
    "noise": official_noise,
    "blur": official_blur,
    "crop": official_crop,
    "jpeg": official_jpeg,
}

#: Robustness-curve sweeps: attack name -> (keyword of the attack function, values: weakest first; brightness
#: and contrast in increasing factor, 1 being the identity).
SWEEPS: dict[str, tuple[str, tuple[float, ...]]] = {
    "noise": ("sigma", (0.0, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3)),
    "jpeg": ("quality", (90, 70, 50, 30, 20, 10)),
    "blur": ("sigma", (0.1, 0.5, 1.0, 1.5, 2.0, 3.0)),
    "crop": ("keep_area", (1.0, 0.8, 0.6, 0.4, 0.3, 0.2, 0.1)),
    "rotation": ("degrees", (0.0, 5.0, 10.0, 15.0, 30.0, 45.0, 90.0)),
    "scaling": ("factor", (1.0, 0.9, 0.75, 0.5, 0.4, 0.25)),
    "brightness": ("factor", (0.5, 0.75, 1.0, 1.25, 1.5, 2.0)),
    "contrast": ("factor", (0.5, 0.75, 1.0, 1.25, 1.5, 2.0)),
}


def sweep(name: str) -> list:
    """Parameter values for a robustness curve of the attack ``name`` (see :data:`SWEEPS` for the order).

    Use with :func:`sweep_parameter`: ``[IMAGE_ATTACKS[name](img, **{sweep_parameter(name): v}) for v in
    sweep(name)]``.

    Args:
        name: one of ``noise`` (sigma), ``jpeg`` (quality), ``blur`` (sigma), ``crop`` (keep_area),
            ``rotation`` (degrees), ``scaling``, ``brightness``, ``contrast`` (factor).

    Returns:
        A new list of values.
    """
    if name not in SWEEPS:
        raise KeyError(f"no sweep for {name!r}; choose from {sorted(SWEEPS)}")
    return list(SWEEPS[name][1])


def sweep_parameter(name: str) -> str:
    """Keyword argument of ``IMAGE_ATTACKS[name]`` that :func:`sweep` varies.

    Args:
        name: a key of :data:`SWEEPS`.

    Returns:
        The keyword name.
    """
    if name not in SWEEPS:
        raise KeyError(f"no sweep for {name!r}; choose from {sorted(SWEEPS)}")
    return SWEEPS[name][0]


# --------------------------------------------------------------------------------------------- model attacks

#: Raw parameter fields of :class:`Gaussians`, in canonical order.
MODEL_FIELDS: tuple[str, ...] = ("means", "log_scales", "quats", "opacity_logits", "sh")


def _check_fraction(fraction: float) -> None:
    _check_range("fraction", fraction, 0.0, 1.0)


def _fresh(g: Gaussians) -> Gaussians:
    return g.detach().clone()


def parameter_noise(
    g: Gaussians,
    sigma: float = 0.1,
    seed: int = 0,
    fields: Sequence[str] = MODEL_FIELDS,
) -> Gaussians:
    """Add i.i.d. ``N(0, sigma^2)`` to raw (pre-activation) parameters.

    Paper: "Gaussian noise sigma 0.1 on the parameters". By default the noise goes on **all raw
    parameters**: ``means`` (world units), ``log_scales`` (log space), ``quats`` (unnormalised),
    ``opacity_logits`` (pre-sigmoid) and every SH coefficient ``sh`` (DC and higher orders). Noise is drawn in
    float32 on the CPU, field by field in the order of :data:`MODEL_FIELDS`, from one generator (so the noise
    of a field does not depend on which other fields are chosen).

    Args:
        g: input Gaussians (not modified).
        sigma: noise standard deviation, ``>= 0``.
        seed: noise seed.
        fields: subset of :data:`MODEL_FIELDS` to perturb.

    Returns:
        New Gaussians (no tensor shared with ``g``).
    """
    if sigma < 0:
        raise ValueError(f"sigma must be >= 0, got {sigma}")
    chosen = set(fields)
    unknown = chosen - set(MODEL_FIELDS)
    if unknown:
        raise ValueError(f"unknown fields {sorted(unknown)}; choose from {MODEL_FIELDS}")
    gen = _generator(seed)
    params = _fresh(g).parameters()
    for name in MODEL_FIELDS:
        t = params[name]
        noise = torch.randn(t.shape, generator=gen, dtype=torch.float32)
        if name in chosen:
            params[name] = t + sigma * noise.to(device=t.device, dtype=t.dtype)
    return Gaussians(**params)


def parameter_noise_attributes(g: Gaussians, sigma: float = 0.1, seed: int = 0) -> Gaussians:
    """:func:`parameter_noise` on every field except the positions (``log_scales``, ``quats``,
    ``opacity_logits``, ``sh``).

    sigma 0.1 on the ``means`` moves every Gaussian by ~0.17 world units (on lego, ~60 px at 800x800), which
    leaves no usable model to protect; without them the attacked model still renders the scene, which is
    the reading of the paper's "noise on the parameters" under which its numbers (89 %) are possible.
    """
    return parameter_noise(g, sigma, seed, fields=tuple(f for f in MODEL_FIELDS if f != "means"))


def remove_random(g: Gaussians, fraction: float = 0.2, seed: int = 0) -> Gaussians:
    """Delete ``round(fraction * N)`` Gaussians chosen uniformly without replacement.

    The survivors keep their original order. Paper setting: 20 %.

    Args:
        g: input Gaussians (not modified).
        fraction: fraction removed, in ``[0, 1]`` (count rounded half up).
        seed: seed of the choice.

    Returns:
        New Gaussians with ``N - round(fraction * N)`` entries.
    """
    _check_fraction(fraction)
    n = len(g)
    k = _round_half_up(fraction * n)
    perm = torch.randperm(n, generator=_generator(seed))
    keep = perm[k:].sort().values.to(g.device)
    return _fresh(g)[keep]


def clone_random(g: Gaussians, fraction: float = 0.2, seed: int = 0) -> Gaussians:
    """Duplicate ``round(fraction * N)`` Gaussians chosen uniformly without replacement.

    The clones are **exact copies** (same position, scale, rotation, opacity and colour) appended after
    the original ``N`` Gaussians in ascending index order. Note that an exact duplicate changes the render
    (the same splat composited twice, so it becomes more opaque). Paper setting: 20 %.

    Args:
        g: input Gaussians (not modified).
        fraction: fraction duplicated, in ``[0, 1]`` (count rounded half up).
        seed: seed of the choice.

    Returns:
        New Gaussians with ``N + round(fraction * N)`` entries; the first ``N`` equal ``g``.
    """
    _check_fraction(fraction)
    n = len(g)
    k = _round_half_up(fraction * n)
    idx = torch.randperm(n, generator=_generator(seed))[:k].sort().values.to(g.device)
    base = _fresh(g)
    return cat_gaussians([base, base[idx]])


def reduce_sh(g: Gaussians, degree: int = 0) -> Gaussians:
    """Drop the SH coefficients above ``degree`` (degree 0 keeps only the DC, i.e. view-independent colour).

    Args:
        g: input Gaussians (not modified).
        degree: target SH degree, ``0 <= degree <= g.sh_degree``.

    Returns:
        New Gaussians with ``sh [N, (degree + 1)^2, 3]``, the kept coefficients unchanged.
    """
    if not isinstance(degree, int) or isinstance(degree, bool) or not 0 <= degree <= g.sh_degree:
        raise ValueError(f"degree must be an int in 0..{g.sh_degree} (the model's degree), got {degree!r}")
    return _fresh(g.with_sh_degree(degree))


def prune_by_opacity(g: Gaussians, fraction: float = 0.5) -> Gaussians:
    """Remove the ``round(fraction * N)`` Gaussians of lowest opacity (deterministic).

    Ties are broken by index (stable sort: the lower index is removed first); survivors keep their order.

    Args:
        g: input Gaussians (not modified).
        fraction: fraction removed, in ``[0, 1]`` (count rounded half up).

    Returns:
        New Gaussians with the ``N - round(fraction * N)`` most opaque entries.
    """
    _check_fraction(fraction)
    n = len(g)
    k = _round_half_up(fraction * n)
    order = torch.sort(g.opacity_logits.detach(), stable=True).indices
    keep = order[k:].sort().values
    return _fresh(g)[keep]


def _quantize_columns(t: Tensor, bits: int) -> Tensor:
    n = t.shape[0]
    if n == 0:
        return t.clone()
    x = t.detach().reshape(n, -1).to(torch.float64)
    lo = x.min(dim=0).values
    hi = x.max(dim=0).values
    rng = hi - lo
    levels = 2**bits - 1
    step = torch.where(rng > 0, rng / levels, torch.ones_like(rng))
    q = torch.round((x - lo) / step).clamp(0, levels)
    y = torch.where(rng > 0, lo + q * step, x)
    return y.to(t.dtype).reshape(t.shape)


def quantize(g: Gaussians, bits: int = 8) -> Gaussians:
    """Per-column min-max uniform quantisation of every raw attribute, dequantised back.

    Every scalar column (``means[:, j]``, ``log_scales[:, j]``, ``quats[:, j]``, ``opacity_logits``,
    ``sh[:, k, c]``) is mapped to ``2^bits`` levels between its own min and max (computed in float64) and
    back, so the error per element is at most ``(max - min) / (2 * (2^bits - 1))`` (``range / 510`` for
    8 bits), plus the final cast to the model's dtype. Constant columns are unchanged.

    Args:
        g: input Gaussians (not modified).
        bits: bits per value, ``1..16``.

    Returns:
        New Gaussians with quantised values.
    """
    if not isinstance(bits, int) or isinstance(bits, bool) or not 1 <= bits <= 16:
        raise ValueError(f"bits must be an int in 1..16, got {bits!r}")
    return Gaussians(**{name: _quantize_columns(t, bits) for name, t in g.parameters().items()})


def finetune(g: Gaussians, cameras: Sequence["Camera"], *, steps: int = 300, quality: int | None = 50,
             background: tuple[float, float, float] = (0.0, 0.0, 0.0), seed: int = 0) -> Gaussians:
    """Fine-tunes the model for ``steps`` iterations on its own renders (an attacker without the photos).

    The targets are the model's renders of ``cameras``, laundered through real JPEG at ``quality`` (the
    attacker's attempt to wash the watermark out of the training targets; ``None`` keeps the renders as
    they are, so the loss starts at zero and the attack only checks that plain fine-tuning keeps the
    mark). Training is :func:`gsw.train.train` started from ``g`` with INRIA's fine-stage settings: L1 +
    0.2 D-SSIM, Adam on every parameter (positions at the final INRIA rate ``1.6e-6 x extent``), one view
    per step, no densification and no opacity reset. Runs on ``g``'s device and needs the compiled
    extension.

    Args:
        g: input Gaussians (not modified).
        cameras: the views the attacker renders and trains on.
        steps: optimisation steps, ``>= 1``.
        quality: JPEG quality of the targets in ``1..100``, or None for the plain renders.
        background: render background.
        seed: view order.

    Returns:
        New, fine-tuned Gaussians.
    """
    from gsw.render.rasterize import rasterize
    from gsw.train import TrainConfig, train

    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be an int >= 1, got {steps!r}")
    if not cameras:
        raise ValueError("finetune needs at least one camera")
    with torch.no_grad():
        targets = torch.stack([rasterize(g, cam, background=background).image.clamp(0.0, 1.0) for cam in cameras])
    if quality is not None:
        targets = jpeg(targets, quality=quality)
    cfg = TrainConfig(iterations=steps, sh_degree=g.sh_degree, position_lr_init=TrainConfig.position_lr_final,
                      densify_until_iter=0, opacity_reset_interval=0, seed=seed, log_interval=steps,
                      device=str(g.device))
    with torch.enable_grad():
        return train((list(cameras), targets), config=cfg, init=_fresh(g), progress=False,
                     background=background).gaussians


#: Model attacks at the paper's strengths (plus the extra ones at their defaults); call as ``fn(g)``.
MODEL_ATTACKS: dict[str, Callable[[Gaussians], Gaussians]] = {
    "parameter_noise": parameter_noise,
    "parameter_noise_attributes": parameter_noise_attributes,
    "remove": remove_random,
    "clone": clone_random,
    "reduce_sh": reduce_sh,
    "prune_by_opacity": prune_by_opacity,
    "quantize": quantize,
}

#: Model attacks that render the model, at their defaults; call as ``fn(g, cameras, background=bg)``
#: (:func:`bind_model_attacks` turns them into ``fn(g)``).
VIEW_MODEL_ATTACKS: dict[str, Callable[..., Gaussians]] = {
    "finetune": finetune,
}


ModelAttack = Callable[[Gaussians], Gaussians]


#: Every model attack name (:data:`MODEL_ATTACKS` and :data:`VIEW_MODEL_ATTACKS`).
MODEL_ATTACK_NAMES: tuple[str, ...] = (*MODEL_ATTACKS, *VIEW_MODEL_ATTACKS)


def bind_model_attacks(names: Sequence[str], cameras: Sequence["Camera"],
                       background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> dict[str, ModelAttack]:
    """Model attacks by name, as ``fn(g)``: those of :data:`VIEW_MODEL_ATTACKS` bound to ``cameras``.

    Args:
        names: keys of :data:`MODEL_ATTACKS` or :data:`VIEW_MODEL_ATTACKS`.
        cameras: the views a view attack renders (e.g. the embedding views).
        background: their render background.

    Returns:
        name -> attack.
    """
    unknown = [n for n in names if n not in MODEL_ATTACK_NAMES]
    if unknown:
        raise KeyError(f"unknown model attacks {unknown}; choose from {list(MODEL_ATTACK_NAMES)}")
    return {n: MODEL_ATTACKS[n] if n in MODEL_ATTACKS else
            functools.partial(VIEW_MODEL_ATTACKS[n], cameras=list(cameras), background=tuple(background))
            for n in names}
