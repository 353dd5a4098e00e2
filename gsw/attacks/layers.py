"""Noise layers (image attacks) for decoder pre-training and robustness evaluation.

Every layer maps images [B,3,H,W] with values in [0,1] to attacked images (same batch, possibly another
size), is differentiable or straight-through, and draws its random parameters from an optional
``torch.Generator`` (seeded => reproducible).  Each layer has a parameter range ``(weakest, strongest)``
(default: :data:`gsw.attacks.presets.TRAINING_RANGES`); a draw is ``weakest + t (strongest - weakest)`` with
``t ~ U(0, strength)``, so ``strength`` (default 1) can ramp the attacks up during training.  ``fixed=True``
always uses ``strongest`` (evaluation; :func:`paper_attacks` are the paper's strengths as fixed layers).

Layers: :class:`Identity`, :class:`Crop`, :class:`Resize`, :class:`JPEG`, :class:`GaussianBlur`,
:class:`GaussianNoise`, :class:`Rotation`, :class:`Combined`.

JPEG: ``mode="real"`` runs the real codec of :func:`gsw.attacks.ops.jpeg` (Pillow's libjpeg, 4:2:0 chroma
subsampling, uint8) in the forward pass with an identity (straight-through) gradient; ``mode="diff"`` uses
kornia's differentiable JPEG (Reich et al. 2024); ``mode="real_diffgrad"`` (default) outputs the real JPEG
and back-propagates through kornia's differentiable JPEG: ``y = diff + (real - diff).detach()``.

Example:
    >>> import torch
    >>> g = torch.Generator().manual_seed(0)
    >>> x = torch.rand(4, 3, 64, 64)
    >>> Crop(area=(1.0, 0.25), fixed=True)(x, generator=g).shape
    torch.Size([4, 3, 32, 32])
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from gsw.attacks.ops import gaussian_kernel1d, jpeg, separable_blur
from gsw.attacks.presets import PAPER_IMAGE_ATTACKS, TRAINING_COMBINED_RANGES, TRAINING_RANGES

__all__ = [
    "GpuAttacks",
    "TRAINING_LAYER_NAMES",
    "NoiseLayer",
    "Identity",
    "Crop",
    "Resize",
    "JPEG",
    "GaussianBlur",
    "GaussianNoise",
    "Rotation",
    "Combined",
    "real_jpeg",
    "diff_jpeg",
    "quantize_st",
    "clamp_st",
    "training_noise_layers",
    "matched_noise_layers",
    "paper_attacks",
]


def clamp_st(x: torch.Tensor) -> torch.Tensor:
    """Clamp to [0,1] in the forward pass, identity gradient."""
    return x + (x.clamp(0.0, 1.0) - x).detach()


def quantize_st(x: torch.Tensor) -> torch.Tensor:
    """Clamp to [0,1] and round to 1/255 in the forward pass, identity gradient."""
    return x + ((x.clamp(0.0, 1.0) * 255.0).round() / 255.0 - x).detach()


def _rand(generator: torch.Generator | None, n: int = 1) -> torch.Tensor:
    dev = generator.device if generator is not None else "cpu"
    return torch.rand(n, generator=generator, device=dev).cpu()


class NoiseLayer(nn.Module):
    """Base class. Subclasses implement ``apply(x, params [B], generator)``."""

    name = "noise"

    def __init__(self, weakest: float, strongest: float, fixed: bool = False, per_sample: bool = True) -> None:
        super().__init__()
        self.weakest, self.strongest = float(weakest), float(strongest)
        self.fixed = fixed
        self.per_sample = per_sample
        self.strength = 1.0

    def sample(self, batch: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Parameters [batch] (float64, CPU)."""
        if self.fixed:
            return torch.full((batch,), self.strongest, dtype=torch.float64)
        t = _rand(generator, batch if self.per_sample else 1).double() * self.strength
        p = self.weakest + t * (self.strongest - self.weakest)
        return p if self.per_sample else p.expand(batch).clone()

    def forward(self, x: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """x [B,3,H,W] in [0,1] -> attacked images."""
        return self.apply(x, self.sample(x.shape[0], generator), generator)

    def apply(self, x: torch.Tensor, params: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        raise NotImplementedError

    def extra_repr(self) -> str:
        return f"range=({self.weakest}, {self.strongest}), fixed={self.fixed}"


class Identity(NoiseLayer):
    """No attack."""

    name = "identity"

    def __init__(self) -> None:
        super().__init__(0.0, 0.0, fixed=True)

    def apply(self, x, params, generator):
        return x


class Crop(NoiseLayer):
    """Keep a random window holding a fraction ``area`` of the image (same aspect ratio), no resize.

    One window size per batch (the batch stays one tensor), a random position per image.
    """

    name = "crop"

    def __init__(self, area: tuple[float, float] = TRAINING_RANGES["crop"], fixed: bool = False) -> None:
        super().__init__(area[0], area[1], fixed, per_sample=False)

    def apply(self, x, params, generator):
        h, w = x.shape[-2:]
        side = math.sqrt(float(params[0]))
        ch, cw = max(4, round(h * side)), max(4, round(w * side))
        ch, cw = min(ch, h), min(cw, w)
        oy = (_rand(generator, x.shape[0]) * (h - ch + 1)).long().clamp_max(h - ch)
        ox = (_rand(generator, x.shape[0]) * (w - cw + 1)).long().clamp_max(w - cw)
        return torch.stack([x[i, :, oy[i] : oy[i] + ch, ox[i] : ox[i] + cw] for i in range(x.shape[0])])


class Resize(NoiseLayer):
    """Rescale both sides by ``scale`` (bilinear, antialiased); one scale per batch."""

    name = "resize"

    def __init__(self, scale: tuple[float, float] = TRAINING_RANGES["resize"], fixed: bool = False) -> None:
        super().__init__(scale[0], scale[1], fixed, per_sample=False)

    def apply(self, x, params, generator):
        s = float(params[0])
        h, w = x.shape[-2:]
        size = (max(4, round(h * s)), max(4, round(w * s)))
        if size == (h, w):
            return x
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)


@torch.no_grad()
def real_jpeg(x: torch.Tensor, quality: torch.Tensor | float) -> torch.Tensor:
    """Real JPEG round trip (:func:`gsw.attacks.ops.jpeg`: Pillow, 4:2:0) with a quality per image.

    Args:
        x: [B,3,H,W] in [0,1] (clamped and rounded to uint8 first).
        quality: scalar or per-image [B] quality in 1..100 (rounded).

    Returns:
        [B,3,H,W], multiples of 1/255; not differentiable.
    """
    q = torch.as_tensor(quality).flatten().expand(x.shape[0]).round().int().tolist()
    return torch.cat([jpeg(x[i : i + 1], quality=q[i]) for i in range(x.shape[0])])


def diff_jpeg(x: torch.Tensor, quality: torch.Tensor) -> torch.Tensor:
    """kornia's differentiable JPEG, x [B,3,H,W] in [0,1], quality [B]."""
    from kornia.enhance import jpeg_codec_differentiable

    q = torch.as_tensor(quality, dtype=torch.float32, device=x.device).flatten().expand(x.shape[0])
    return jpeg_codec_differentiable(x.float().clamp(0, 1), q.contiguous()).to(x.dtype)


class JPEG(NoiseLayer):
    """JPEG compression with quality in ``quality`` (per image); see module docstring for ``mode``."""

    name = "jpeg"

    def __init__(
        self, quality: tuple[float, float] = TRAINING_RANGES["jpeg"], mode: str = "real_diffgrad",
        fixed: bool = False,
    ) -> None:
        super().__init__(quality[0], quality[1], fixed)
        if mode not in ("real", "diff", "real_diffgrad"):
            raise ValueError(f"unknown JPEG mode {mode!r}")
        self.mode = mode

    def apply(self, x, params, generator):
        q = params.round()
        if self.mode == "diff":
            return diff_jpeg(x, q)
        real = real_jpeg(x, q)
        if self.mode == "real":
            return x + (real - x).detach()
        d = diff_jpeg(x, q)
        return d + (real - d).detach()


def _blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian blur of x [B,C,H,W] with std ``sigma`` pixels: kernel radius ceil(3 sigma), at least 1 and at
    most the image size - 1 (reflect padding), no clamping."""
    r = min(max(1, math.ceil(3.0 * sigma)), x.shape[-1] - 1, x.shape[-2] - 1)
    return separable_blur(x, gaussian_kernel1d(sigma, 2 * r + 1, dtype=x.dtype).to(x.device))


class GaussianBlur(NoiseLayer):
    """Gaussian blur with std ``sigma`` pixels (one sigma per batch), kernel radius ceil(3 sigma),
    reflect padding."""

    name = "blur"

    def __init__(self, sigma: tuple[float, float] = TRAINING_RANGES["blur"], fixed: bool = False) -> None:
        super().__init__(sigma[0], sigma[1], fixed, per_sample=False)

    def apply(self, x, params, generator):
        return _blur(x, float(params[0]))


class GaussianNoise(NoiseLayer):
    """Additive white Gaussian noise of std ``std`` (per image), then clamp to [0,1] (straight-through)."""

    name = "noise"

    def __init__(self, std: tuple[float, float] = TRAINING_RANGES["noise"], fixed: bool = False) -> None:
        super().__init__(std[0], std[1], fixed)

    def apply(self, x, params, generator):
        dev = generator.device if generator is not None else x.device
        n = torch.randn(x.shape, generator=generator, device=dev, dtype=torch.float32).to(x.device, x.dtype)
        return clamp_st(x + n * params.to(x.device, x.dtype).view(-1, 1, 1, 1))


class Rotation(NoiseLayer):
    """Rotate about the centre by +-``degrees`` (random sign per image), bilinear, black corners."""

    name = "rotation"

    def __init__(self, degrees: tuple[float, float] = TRAINING_RANGES["rotation"], fixed: bool = False) -> None:
        super().__init__(degrees[0], degrees[1], fixed)

    def apply(self, x, params, generator):
        sign = (_rand(generator, x.shape[0]) < 0.5).double() * 2 - 1
        a = torch.deg2rad(params * sign)
        h, w = x.shape[-2:]
        cos, sin = torch.cos(a), torch.sin(a)
        # affine_grid works in normalised coords; correct for the aspect ratio
        theta = torch.zeros(x.shape[0], 2, 3, dtype=torch.float64)
        theta[:, 0, 0], theta[:, 0, 1] = cos, -sin * h / w
        theta[:, 1, 0], theta[:, 1, 1] = sin * w / h, cos
        grid = F.affine_grid(theta.to(x.device, torch.float32), list(x.shape), align_corners=False)
        return F.grid_sample(x.float(), grid, mode="bilinear", padding_mode="zeros", align_corners=False).to(
            x.dtype
        )


class Combined(NoiseLayer):
    """Apply several layers in sequence (e.g. crop -> blur -> JPEG)."""

    name = "combined"

    def __init__(self, layers: list[NoiseLayer]) -> None:
        super().__init__(0.0, 0.0, fixed=True)
        self.layers = nn.ModuleList(layers)

    @property
    def strength(self) -> float:  # type: ignore[override]
        return self._strength

    @strength.setter
    def strength(self, v: float) -> None:
        self._strength = v
        for layer in getattr(self, "layers", []):
            layer.strength = v

    def forward(self, x, generator=None):
        for layer in self.layers:
            x = layer(x, generator=generator)
        return x


def draws_per_batch(layer: NoiseLayer) -> bool:
    """Whether ``layer`` (or a layer inside a :class:`Combined`) draws one random strength for a whole batch."""
    if not layer.fixed and not layer.per_sample:
        return True
    return any(draws_per_batch(sub) for sub in getattr(layer, "layers", []))


def training_noise_layers(jpeg_mode: str = "real_diffgrad") -> dict[str, NoiseLayer]:
    """The pre-training noise layers at their ranges (:data:`gsw.attacks.presets.TRAINING_RANGES`)."""
    c = TRAINING_COMBINED_RANGES
    return {
        "identity": Identity(),
        "crop": Crop(),
        "resize": Resize(),
        "jpeg": JPEG(mode=jpeg_mode),
        "blur": GaussianBlur(),
        "noise": GaussianNoise(),
        "rotation": Rotation(),
        "combined": Combined([Crop(area=c["crop"]), GaussianBlur(sigma=c["blur"]), JPEG(c["jpeg"], jpeg_mode)]),
    }


def matched_noise_layers(jpeg_mode: str = "real_diffgrad") -> dict[str, NoiseLayer]:
    """Training layers whose strongest draw is the evaluation's strength (train-time attack sampling that
    matches :func:`paper_attacks`): each paper attack from none up to its paper strength
    (:data:`gsw.attacks.presets.PAPER_IMAGE_ATTACKS`), blur up to the training range's 2 px, and the
    combined crop -> blur -> JPEG at the paper's strengths. No identity layer."""
    p = PAPER_IMAGE_ATTACKS
    c = p["combined"]
    q = float(p["jpeg"]["quality"])
    return {
        "crop": Crop(area=(1.0, p["crop"]["keep_area"])),
        "resize": Resize(scale=(1.0, min(p["scaling"]["factor"], TRAINING_RANGES["resize"][1]))),
        "jpeg": JPEG(quality=(90.0, q), mode=jpeg_mode),
        "blur": GaussianBlur(sigma=(p["blur"]["sigma"], max(p["blur"]["sigma"], TRAINING_RANGES["blur"][1]))),
        "noise": GaussianNoise(std=(0.0, p["noise"]["sigma"])),
        "rotation": Rotation(degrees=(0.0, p["rotation"]["degrees"])),
        "combined": Combined([Crop(area=(1.0, c["keep_area"])), GaussianBlur(sigma=(c["blur_sigma"],) * 2),
                              JPEG((90.0, float(c["quality"])), jpeg_mode)]),
    }


def paper_attacks() -> dict[str, NoiseLayer]:
    """The 3D-GSW paper's image attacks (:data:`gsw.attacks.presets.PAPER_IMAGE_ATTACKS`) as fixed layers.

    Named by their strengths (``noise_std0.1``, ..., ``combined_crop0.4_blur0.1_jpeg50``). The layers follow
    the training layers' conventions (random crop position and rotation sign, JPEG through
    :func:`real_jpeg`), not those of the deterministic :data:`gsw.attacks.presets.IMAGE_ATTACKS`.
    """
    p = PAPER_IMAGE_ATTACKS
    std, deg, scale = p["noise"]["sigma"], p["rotation"]["degrees"], p["scaling"]["factor"]
    sigma, area, q = p["blur"]["sigma"], p["crop"]["keep_area"], p["jpeg"]["quality"]
    c = p["combined"]
    return {
        f"noise_std{std:g}": GaussianNoise(std=(std, std), fixed=True),
        f"rotation_{deg:g}deg": Rotation(degrees=(deg, deg), fixed=True),
        f"scale_{scale:g}": Resize(scale=(scale, scale), fixed=True),
        f"blur_sigma{sigma:g}": GaussianBlur(sigma=(sigma, sigma), fixed=True),
        f"crop_area{area:g}": Crop(area=(area, area), fixed=True),
        f"jpeg_q{q:g}": JPEG(quality=(q, q), mode="real", fixed=True),
        f"combined_crop{c['keep_area']:g}_blur{c['blur_sigma']:g}_jpeg{c['quality']:g}": Combined([
            Crop((c["keep_area"],) * 2, True), GaussianBlur((c["blur_sigma"],) * 2, True),
            JPEG((c["quality"],) * 2, "real", True)]),
    }


#: The training noise layers in the order the pre-training and the optimisation encoder cycle through them.
TRAINING_LAYER_NAMES: tuple[str, ...] = ("identity", "crop", "resize", "jpeg", "blur", "noise", "rotation", "combined")


def _rot2(a: torch.Tensor) -> torch.Tensor:
    """[B] angles (radians) -> [B,2,2] rotation matrices."""
    c, s = torch.cos(a), torch.sin(a)
    return torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], 1)


def _affine(x: torch.Tensor, lin: torch.Tensor, padding: str) -> torch.Tensor:
    """Resample x [B,C,H,W] (bilinear) so that output pixel p (pixel units, from the centre) shows input
    pixel lin[b] @ p; lin [B,2,2] acts on (x, y)."""
    B, _, H, W = x.shape
    aspect = torch.tensor([[1.0, H / W], [W / H, 1.0]], device=x.device, dtype=lin.dtype)  # pixels -> [-1,1]
    theta = torch.cat([lin * aspect, torch.zeros(B, 2, 1, device=x.device, dtype=lin.dtype)], -1)
    grid = F.affine_grid(theta, [B, x.shape[1], H, W], align_corners=False)
    return F.grid_sample(x.float(), grid, mode="bilinear", padding_mode=padding, align_corners=False)


class GpuAttacks:
    """Device-only training attacks, same names and ranges as :func:`training_noise_layers`.

    ``apply(name, x, strength)``: per-batch parameters (crop size, resize scale, blur sigma) come from the
    host RNG, per-image ones (crop position, JPEG quality, noise std, rotation angle) from the device
    generator; a parameter is ``weakest + t (strongest - weakest)``, ``t ~ U(0, strength)``.  JPEG is kornia's
    differentiable codec.
    """

    def __init__(self, device: torch.device, seed: int) -> None:
        import random

        self.device = torch.device(device)
        self.rng = random.Random(seed)
        self.gen = torch.Generator(device=self.device).manual_seed(seed + 1)

    def _t(self, s: float) -> float:
        return self.rng.random() * s

    def _tv(self, n: int, s: float) -> torch.Tensor:
        return torch.rand(n, device=self.device, generator=self.gen) * s

    def crop(self, x: torch.Tensor, s: float, area: tuple[float, float] = TRAINING_RANGES["crop"]) -> torch.Tensor:
        B, _, H, W = x.shape
        weakest, strongest = area
        side = math.sqrt(weakest + self._t(s) * (strongest - weakest))
        ch, cw = min(H, max(4, round(H * side))), min(W, max(4, round(W * side)))
        if (ch, cw) == (H, W):
            return x
        u = torch.rand(B, 2, device=x.device, generator=self.gen)
        oy = (u[:, 0] * (H - ch + 1)).long().clamp_max(H - ch)
        ox = (u[:, 1] * (W - cw + 1)).long().clamp_max(W - cw)
        ry = oy[:, None] + torch.arange(ch, device=x.device)
        rx = ox[:, None] + torch.arange(cw, device=x.device)
        b = torch.arange(B, device=x.device)[:, None, None]
        return x[b, :, ry[:, :, None], rx[:, None, :]].permute(0, 3, 1, 2)

    def resize(self, x: torch.Tensor, s: float) -> torch.Tensor:
        weakest, strongest = TRAINING_RANGES["resize"]
        sc = weakest + self._t(s) * (strongest - weakest)
        H, W = x.shape[-2:]
        size = (max(4, round(H * sc)), max(4, round(W * sc)))
        if size == (H, W):
            return x
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)

    def jpeg(self, x: torch.Tensor, s: float,
             quality: tuple[float, float] = TRAINING_RANGES["jpeg"]) -> torch.Tensor:
        q_hi, q_lo = quality
        q = (q_hi + self._tv(x.shape[0], s) * (q_lo - q_hi)).round()
        return diff_jpeg(x.float(), q)

    def blur(self, x: torch.Tensor, s: float,
             sigma: tuple[float, float] = TRAINING_RANGES["blur"]) -> torch.Tensor:
        lo, hi = sigma
        return _blur(x, lo + self._t(s) * (hi - lo))

    def noise(self, x: torch.Tensor, s: float) -> torch.Tensor:
        weakest, strongest = TRAINING_RANGES["noise"]
        std = weakest + self._tv(x.shape[0], s) * (strongest - weakest)
        n = torch.randn(x.shape, device=x.device, generator=self.gen, dtype=x.dtype)
        return clamp_st(x + n * std.view(-1, 1, 1, 1).to(x.dtype))

    def rotation(self, x: torch.Tensor, s: float) -> torch.Tensor:
        B = x.shape[0]
        u = torch.rand(B, 2, device=x.device, generator=self.gen)
        weakest, strongest = TRAINING_RANGES["rotation"]
        a = torch.deg2rad((weakest + (strongest - weakest) * u[:, 0] * s) * torch.where(u[:, 1] < 0.5, -1.0, 1.0))
        return _affine(x, _rot2(a), "zeros")

    def view(self, x: torch.Tensor, s: float, max_zoom: float = 1.4, min_foreshortening: float = 0.5) -> torch.Tensor:
        """What another viewpoint does to a surface texture, to first order: a random affine map per image,
        in-plane rotation uniform in +-180 s degrees, isotropic zoom in [1/max_zoom, max_zoom]^s (log-uniform)
        and foreshortening by a factor in [1 - s (1 - min_foreshortening), 1] along a random direction;
        reflection padding, bilinear.  A 3DGS can only carry a watermark that survives this (a decoder
        trained without it reads an image-space pattern that no multi-view consistent scene produces)."""
        B = x.shape[0]
        u = torch.rand(B, 4, device=x.device, generator=self.gen)
        a = (u[:, 0] * 2.0 - 1.0) * math.pi * s
        zoom = torch.exp((u[:, 1] * 2.0 - 1.0) * math.log(max_zoom) * s)
        f = 1.0 - u[:, 2] * s * (1.0 - min_foreshortening)
        phi = u[:, 3] * math.pi
        rphi = _rot2(phi)
        squash = torch.diag_embed(torch.stack([1.0 / f, torch.ones_like(f)], -1))
        return _affine(x, _rot2(a) @ rphi @ squash @ rphi.transpose(1, 2) * zoom.view(B, 1, 1), "reflection")

    def combined(self, x: torch.Tensor, s: float) -> torch.Tensor:
        c = TRAINING_COMBINED_RANGES
        x = self.crop(x, s, area=c["crop"])
        x = self.blur(x, s, sigma=c["blur"])
        return self.jpeg(x, s, quality=c["jpeg"])

    def identity(self, x: torch.Tensor, s: float) -> torch.Tensor:
        return x

    def apply(self, name: str, x: torch.Tensor, strength: float) -> torch.Tensor:
        return getattr(self, name)(x, strength)
