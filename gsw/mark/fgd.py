"""Frequency-guided densification (FGD), the model-side preparation of 3D-GSW.

Phase 1 (:func:`fgd_prune`) removes Gaussians that contribute (almost) nothing to any training
view; phase 2 (:func:`fgd_split`) splits the low-contribution Gaussians that cover the most
high-frequency image patches, giving the watermark capacity where it hides best.

Departures from the official code, on purpose (see GUIDE section 2):

* Phase 1 normalises the contribution as the official code's loss does (a mean over the 3 H W elements of
  the error-weighted render), so the threshold does not depend on the resolution and the default 1e-8 is
  the paper's value on that loss. As in the official code, a view votes for pruning when any one channel
  is at or below the threshold, and a Gaussian is pruned when every view does.
* Phase 2 uses a true 2-D DFT over (height, width) of each 16x16 patch and channel, and tracks
  Gaussians by their actual contribution to the selected patches (the contribution kernel with a
  patch mask), not by their projected centre.
* Split is deterministic and moment-matched (children along the longest axis, see
  :func:`split_gaussians`), not 3DGS' random sampling with scales / 1.6: positions stay frozen
  during fine-tuning, so nothing would repair a visibly changed render. It still changes the renders
  (36.7-39.7 dB against the input on the models measured, BENCHMARKS.md §9j).

This module imports the rasterizer (it needs the compiled extension).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.gaussians import Gaussians
from gsw.render.rasterize import contribution, rasterize

#: Phase-1 threshold on the normalised contribution (the paper's value on its mean-reduced loss).
PRUNE_THRESHOLD = 1e-8
#: Phase-2 patch size (pixels) and share of patches kept (percent).
PATCH_SIZE = 16
TOP_PERCENT = 1.0


@dataclass
class PruneReport:
    """Phase-1 statistics.

    Attributes:
        num_before: Gaussians before pruning.
        num_removed: Gaussians removed.
        max_contribution: [N] per-Gaussian maximum over views of the smallest channel's normalised
            contribution (before pruning); a Gaussian is pruned when this is <= ``threshold``.
        threshold: the threshold used.
    """

    num_before: int
    num_removed: int
    max_contribution: Tensor
    threshold: float

    @property
    def fraction_removed(self) -> float:
        return self.num_removed / max(1, self.num_before)


@dataclass
class SplitReport:
    """Phase-2 statistics.

    Attributes:
        num_before: Gaussians before splitting.
        num_candidates: Gaussians contributing to the selected high-frequency patches.
        num_split: Gaussians replaced by two children each.
        patches_per_view: number of selected patches in each view.
    """

    num_before: int
    num_candidates: int
    num_split: int
    patches_per_view: list[int]


def _views(cameras: Sequence[Camera], images: Tensor | Sequence[Tensor] | None) -> None:
    if len(cameras) == 0:
        raise ValueError("at least one camera is required")
    if images is not None:
        if len(images) != len(cameras):
            raise ValueError(f"{len(images)} images for {len(cameras)} cameras")
        for i, (img, cam) in enumerate(zip(images, cameras)):
            if tuple(img.shape) != (3, cam.height, cam.width):
                raise ValueError(f"image {i} has shape {list(img.shape)}, camera {i} expects "
                                 f"[3, {cam.height}, {cam.width}]")


@torch.no_grad()
def fgd_prune(gaussians: Gaussians, cameras: Sequence[Camera], images: Sequence[Tensor] | None = None,
              *, threshold: float = PRUNE_THRESHOLD,
              background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[Gaussians, PruneReport]:
    """FGD phase 1: removes Gaussians whose contribution is below `threshold` in every view.

    Per view and channel, `V[i,c] = (1 / (3 H W)) sum_p E[c,p] alpha_i(p) T_i(p)`: the gradient of
    the paper's loss `mean(E * I)` (mean over the 3 H W elements) with respect to a colour override
    of Gaussian `i`, with the paper's error weighting `E = |I_0 - I_gt|`, where `I_0` is the render
    with all colours set to zero (background only) and `I_gt` the training image.

    Without images, `E` is the model's alpha `1 - T_final` (every channel): the paper's weighting with
    the model's own render as `I_gt`, taken for the colours at both extremes (`|I_0 - I| + |I_1 - I|`,
    `I_1` the render with all colours one, sums to the alpha). With the own render alone, `E` is the
    render's colour, so opaque dark Gaussians weigh nearly nothing and were pruned although they hide
    the background (lego 800x800: 47 % more pruned than with the photos and ~3 dB lost after
    embedding; BENCHMARKS.md, #27); the alpha weighs a Gaussian by its blending weight, whatever its
    colour (lego 200x200, 77,762 Gaussians: 615 pruned against 3,294 with the photos and 8,359 with the own
    render; BENCHMARKS.md).

    Args:
        gaussians: the model.
        cameras: the training views.
        images: optional [3, H, W] training images in [0, 1], one per camera.
        threshold: prune when, in every view, some channel's normalised contribution is <= this.
        background: background colour of the renders.

    Returns:
        The pruned model and a :class:`PruneReport`.
    """
    _views(cameras, images)
    n = len(gaussians)
    best = torch.zeros(n, dtype=gaussians.dtype, device=gaussians.device)
    zero_colors = torch.zeros(n, 3, dtype=gaussians.dtype, device=gaussians.device)
    for i, cam in enumerate(cameras):
        if images is not None:
            empty = rasterize(gaussians, cam, colors=zero_colors, background=background).image
            error = (empty - images[i].to(empty)).abs()
        else:
            error = rasterize(gaussians, cam, background=background).alpha.expand(3, -1, -1).contiguous()
        v = contribution(gaussians, cam, error).values / float(error.numel())
        best = torch.maximum(best, v.min(dim=1).values)
    keep = best > threshold
    report = PruneReport(num_before=n, num_removed=int((~keep).sum()), max_contribution=best,
                         threshold=threshold)
    return gaussians[keep], report


def high_frequency_scores(image: Tensor, patch: int = PATCH_SIZE) -> Tensor:
    """High-frequency intensity of each patch: `mean(|F| * Q)` over the centred 2-D spectrum.

    `F` is the 2-D DFT over (height, width) of each patch and channel; `Q[u, v] =
    ((2u - U)/U)^2 + ((2v - V)/V)^2` weights frequencies by their distance from the centre.
    Image borders that do not fill a whole patch are ignored.

    Args:
        image: [3, H, W].
        patch: patch size.

    Returns:
        [H // patch, W // patch] scores.
    """
    c, h, w = image.shape
    ph, pw = h // patch, w // patch
    if ph == 0 or pw == 0:
        raise ValueError(f"image {h}x{w} is smaller than one {patch}x{patch} patch")
    x = image[:, : ph * patch, : pw * patch].reshape(c, ph, patch, pw, patch).permute(1, 3, 0, 2, 4)
    spectrum = torch.fft.fftshift(torch.fft.fft2(x.float(), dim=(-2, -1)), dim=(-2, -1)).abs()
    u = torch.arange(patch, dtype=torch.float32, device=image.device)
    q1 = ((2 * u - patch) / patch) ** 2
    q = q1[:, None] + q1[None, :]
    return (spectrum * q).mean(dim=(-3, -2, -1))


#: Opacity rules of :func:`split_gaussians`.
SPLIT_OPACITY_RULES = ("coincident", "footprint")


def check_opacity_rule(rule: str, name: str = "opacity_rule") -> None:
    """Raises ValueError naming ``name`` unless ``rule`` is one of :data:`SPLIT_OPACITY_RULES`."""
    if rule not in SPLIT_OPACITY_RULES:
        raise ValueError(f"{name} must be one of {SPLIT_OPACITY_RULES}, got {rule!r}")


def split_gaussians(gaussians: Gaussians, mask: Tensor, opacity_rule: str = "coincident") -> Gaussians:
    """Moment-matched split: each selected Gaussian becomes two along its longest axis.

    The children sit at `mean +- s/2 * a` (`a` the longest principal axis, `s` its standard
    deviation) with that axis' standard deviation reduced to `s * sqrt(3)/2`, so the pair has the
    parent's mean and covariance (moment matching); other axes, rotation and SH are copied, and
    each child's opacity is, with ``opacity_rule``:

    * ``"coincident"`` (FGD as measured before BENCHMARKS.md §9j): `1 - sqrt(1 - o)`, what two coincident
      children need to composite to the parent's opacity. Displaced as they are, they composite to ~0.85
      of the parent's alpha at its centre and their footprints add up to ~13 % less than a faint parent's,
      so the split changes the renders (§9j);
    * ``"footprint"``: `1 - (1 - o)^(1 / sqrt(3))`, which is `o / sqrt(3)` for a faint parent: the two
      children's footprints (each `sqrt(3)/2` of the parent's along the axis) add up to the parent's.

    Deterministic. (3DGS instead samples the children from the
    parent and divides all scales by 1.6, which visibly changes a trained model's renders; the
    official 3D-GSW code also keeps the parent.)

    Args:
        gaussians: the model.
        mask: [N] bool, Gaussians to split.
        opacity_rule: one of :data:`SPLIT_OPACITY_RULES` (above).

    Returns:
        The model with the selected Gaussians replaced by their children (N + mask.sum()).
    """
    check_opacity_rule(opacity_rule)
    parents = gaussians[mask]
    if len(parents) == 0:
        return gaussians.clone()
    scales = parents.scales
    axis = scales.argmax(dim=1)
    rows = torch.arange(len(parents), device=scales.device)
    q = parents.rotations
    w, x, y, z = q.unbind(1)
    rot = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=1).view(-1, 3, 3)
    direction = rot[rows, :, axis]  # world-space longest axis (a column of R)
    offset = direction * (0.5 * scales[rows, axis]).unsqueeze(1)
    log_scales = parents.log_scales.clone()
    log_scales[rows, axis] += 0.5 * math.log(0.75)  # s * sqrt(3)/2
    opacity = parents.opacities
    clear = (1 - opacity).clamp_min(0)  # the parent's transmittance at its centre
    kept = torch.sqrt(clear) if opacity_rule == "coincident" else clear ** (1 / math.sqrt(3))
    child_opacity = (1 - kept).clamp(1e-6, 1 - 1e-6)
    children = Gaussians(
        means=torch.cat([parents.means + offset, parents.means - offset]),
        log_scales=log_scales.repeat(2, 1),
        quats=parents.quats.repeat(2, 1),
        opacity_logits=torch.logit(child_opacity).repeat(2),
        sh=parents.sh.repeat(2, 1, 1),
    )
    return Gaussians.cat([gaussians[~mask], children])


@torch.no_grad()
def fgd_split(gaussians: Gaussians, cameras: Sequence[Camera], *, top_percent: float = TOP_PERCENT,
              low_quantile: float = 0.5, patch: int = PATCH_SIZE,
              background: tuple[float, float, float] = (0.0, 0.0, 0.0),
              opacity_rule: str = "coincident") -> tuple[Gaussians, SplitReport]:
    """FGD phase 2: splits the low-contribution Gaussians of the most high-frequency patches.

    For every view: render, score 16x16 patches with :func:`high_frequency_scores`, keep the top
    `top_percent` % (at least one), and compute each Gaussian's contribution to the selected
    pixels (contribution kernel with the patch mask). Gaussians that contribute in any view are
    candidates; those whose summed contribution is at or below the `low_quantile` quantile of
    the candidates are split (:func:`split_gaussians`).

    Args:
        gaussians: the (pruned) model.
        cameras: the training views.
        top_percent: share of patches kept per view, in percent (paper: 1).
        low_quantile: candidates at or below this contribution quantile are split.
        patch: patch size.
        background: background colour of the renders.
        opacity_rule: the children's opacity (:func:`split_gaussians`).

    Returns:
        The densified model and a :class:`SplitReport`.
    """
    _views(cameras, None)
    if not 0 < top_percent <= 100:
        raise ValueError(f"top_percent must be in (0, 100], got {top_percent}")
    n = len(gaussians)
    total = torch.zeros(n, dtype=gaussians.dtype, device=gaussians.device)
    per_view = []
    for cam in cameras:
        image = rasterize(gaussians, cam, background=background).image
        scores = high_frequency_scores(image, patch)
        k = max(1, int(round(scores.numel() * top_percent / 100.0)))
        top = torch.topk(scores.flatten(), k).indices
        mask = torch.zeros(scores.numel(), dtype=image.dtype, device=image.device)
        mask[top] = 1.0
        mask = mask.view_as(scores).repeat_interleave(patch, 0).repeat_interleave(patch, 1)
        weights = torch.zeros(1, cam.height, cam.width, dtype=image.dtype, device=image.device)
        weights[0, : mask.shape[0], : mask.shape[1]] = mask
        total += contribution(gaussians, cam, weights).values[:, 0]
        per_view.append(k)
    candidates = total > 0
    split = torch.zeros_like(candidates)
    if candidates.any():
        cut = torch.quantile(total[candidates].double(), low_quantile).to(total.dtype)
        split = candidates & (total <= cut)
    out = split_gaussians(gaussians, split, opacity_rule)
    return out, SplitReport(num_before=n, num_candidates=int(candidates.sum()),
                            num_split=int(split.sum()), patches_per_view=per_view)
