"""Model attacks on :class:`~gsw.gaussians.Gaussians` (evaluation).

Every attack takes a :class:`Gaussians` and returns new Gaussians whose tensors never alias the input's; the
input is never modified. Random choices are driven by an explicit ``seed`` (a private CPU generator, as for
the image attacks of :mod:`gsw.attacks.ops`). The defaults are the paper's strengths where the paper has
one (noise sigma 0.1 on the parameters, remove 20 %, clone 20 %). :func:`finetune` also renders the model
from given cameras (it needs the compiled extension, imported when it runs); the named tables and
:func:`gsw.attacks.presets.bind_model_attacks` are in :mod:`gsw.attacks.presets`.

Example:
    >>> import torch
    >>> from gsw import attacks
    >>> from gsw.gaussians import Gaussians
    >>> g = Gaussians(torch.zeros(10, 3), torch.zeros(10, 3), torch.ones(10, 4), torch.zeros(10),
    ...               torch.zeros(10, 1, 3))
    >>> len(attacks.remove_random(g, 0.2)), len(attacks.clone_random(g, 0.2))
    (8, 12)
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import torch
from torch import Tensor

from gsw.attacks.ops import _check_range, _generator, _round_half_up, jpeg
from gsw.gaussians import Gaussians, cat_gaussians

if TYPE_CHECKING:
    from gsw.camera import Camera

__all__ = [
    "MODEL_FIELDS",
    "parameter_noise",
    "parameter_noise_attributes",
    "remove_random",
    "clone_random",
    "reduce_sh",
    "prune_by_opacity",
    "quantize",
    "export_splat",
    "export_spz",
    "export_compressed_ply",
    "finetune",
]

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


def _export_roundtrip(g: Gaussians, suffix: str, save, load) -> Gaussians:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"model{suffix}"
        save(g, path)
        return load(path).to(device=g.device, dtype=g.dtype)


def export_splat(g: Gaussians) -> Gaussians:
    """Export to antimatter15 ``.splat`` and load it back with the real codec (:mod:`gsw.io.splat`):
    colours, opacities and rotations as bytes, the SH rest dropped (degree 0).

    Args:
        g: input Gaussians (not modified; at least one).

    Returns:
        New Gaussians (SH degree 0) on ``g``'s device and dtype.
    """
    from gsw.io.splat import load_splat, save_splat

    return _export_roundtrip(g, ".splat", save_splat, load_splat)


def export_spz(g: Gaussians) -> Gaussians:
    """Export to Niantic ``.spz`` (version 3, default precisions) and load it back with the real codec
    (:mod:`gsw.io.spz`): 24-bit fixed-point positions, byte alphas / colours / log-scales, smallest-three
    rotations, SH rest at 5 (degree 1) and 4 bits.

    Args:
        g: input Gaussians (not modified).

    Returns:
        New Gaussians on ``g``'s device and dtype.
    """
    from gsw.io.spz import load_spz, save_spz

    return _export_roundtrip(g, ".spz", save_spz, load_spz)


def export_compressed_ply(g: Gaussians) -> Gaussians:
    """Export to the PlayCanvas / SuperSplat compressed PLY and load it back with the real codec
    (:mod:`gsw.io.compressed_ply`: chunk-wise 11/10/11-bit positions and scales, 8-bit colours, 2-10-10-10
    rotations, 8-bit SH rest).

    Args:
        g: input Gaussians (not modified).

    Returns:
        New Gaussians on ``g``'s device and dtype.
    """
    from gsw.io.compressed_ply import load_compressed_ply, save_compressed_ply

    return _export_roundtrip(g, ".compressed.ply", save_compressed_ply, load_compressed_ply)


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

