"""FGD: phase-1 pruning, phase-2 frequency scores and splitting."""

import math

import pytest
import torch

from gsw.camera import Camera
from gsw.mark.fgd import fgd_prune, fgd_split, high_frequency_scores, split_gaussians
from gsw.gaussians import Gaussians
from gsw.render.rasterize import rasterize
from gsw.scenes import random_gaussians


def _cams(n: int = 3, size: int = 48) -> list[Camera]:
    return [Camera.look_at((3.0 * math.cos(a), 3.0 * math.sin(a), 0.5), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0),
                           0.9, size, size) for a in torch.linspace(0, 1.5, n).tolist()]


def test_prune_removes_invisible_and_transparent_keeps_visible() -> None:
    cams = _cams()
    g = random_gaussians(200, sh_degree=1, seed=0, extent=0.6, opacity_range=(0.3, 0.9))
    g.means[:20] += torch.tensor([0.0, 0.0, 50.0])  # far outside every view
    g.opacity_logits[20:40] = -30.0  # invisible
    pruned, report = fgd_prune(g, cams)
    assert report.num_before == 200
    assert report.max_contribution[:40].max() <= report.threshold
    assert report.num_removed >= 40 and len(pruned) == 200 - report.num_removed
    # What is kept renders (almost) the same: only negligible Gaussians went away.
    for cam in cams:
        a, b = rasterize(g, cam).image, rasterize(pruned, cam).image
        assert (a - b).abs().max() < 1e-3


def test_prune_threshold_is_resolution_independent() -> None:
    # Footprints of several pixels, so the 0.3 px^2 dilation does not dominate at either size.
    g = random_gaussians(150, sh_degree=0, seed=1, extent=0.6, scale_range=(0.06, 0.15))
    small = fgd_prune(g, _cams(2, 64))[1].max_contribution
    large = fgd_prune(g, [c.scaled(2.0) for c in _cams(2, 64)])[1].max_contribution
    visible = small > 1e-6
    ratio = (large[visible] / small[visible]).median()
    assert 0.9 < float(ratio) < 1.1



def test_prune_contribution_is_the_gradient_of_the_mean_reduced_loss() -> None:
    # V[i, c] = d mean(E * I) / d colour[i, c] at colour 0 (the official code's loss, mean over 3 H W); a view
    # keeps a Gaussian only when its smallest channel is above the threshold (the official rule).
    cam = _cams(1, 40)[0]
    g = random_gaussians(60, sh_degree=0, seed=3, extent=0.6, scale_range=(0.05, 0.12)).to(dtype=torch.float64)
    target = torch.rand(3, 40, 40, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    colors = torch.zeros(len(g), 3, dtype=torch.float64, requires_grad=True)
    image = rasterize(g, cam, colors=colors).image
    ((image.detach() - target).abs() * image).mean().backward()
    expected = colors.grad.min(dim=1).values
    got = fgd_prune(g, [cam], [target])[1].max_contribution
    assert torch.allclose(got, expected, rtol=1e-6, atol=1e-15)

def test_prune_without_images_keeps_dark_gaussians_that_hide_the_background() -> None:
    """Without images the weighting is the model's alpha: opaque black Gaussians in front of a white background
    make the render and stay; weighting by the model's own render (the earlier rule, what passing the render as
    ``images`` does) scores them by their colour, zero, and prunes every one."""
    cam = _cams(1, 40)[0]
    g = random_gaussians(12, sh_degree=0, seed=4, extent=0.5, scale_range=(0.08, 0.15), opacity_range=(0.8, 0.95))
    g.sh[:] = (0.0 - 0.5) / 0.28209479177387814  # SH DC of colour 0: black
    white = (1.0, 1.0, 1.0)
    own = rasterize(g, cam, background=white)
    seen = own.radii > 0
    assert int(seen.sum()) >= 6 and float(own.alpha.max()) > 0.5
    by_colour = fgd_prune(g, [cam], [own.image], background=white)[1]
    assert by_colour.num_removed == len(g)  # the old rule: an empty model
    pruned, by_alpha = fgd_prune(g, [cam], background=white)
    assert (by_alpha.max_contribution[seen] > by_alpha.threshold).all()
    assert (rasterize(pruned, cam, background=white).image - own.image).abs().max() < 1e-3


def test_high_frequency_scores_see_both_directions() -> None:
    h = w = 32
    x = torch.arange(w, dtype=torch.float32)
    vertical_stripes = (torch.sin(x * math.pi / 2) > 0).float().expand(3, h, w).clone()
    horizontal_stripes = vertical_stripes.transpose(1, 2).contiguous()
    flat = torch.full((3, h, w), 0.5)
    s_v, s_h, s_f = (high_frequency_scores(im) for im in (vertical_stripes, horizontal_stripes, flat))
    assert s_v.shape == (2, 2)
    assert torch.allclose(s_v, s_h.T, rtol=1e-4)  # a true 2-D DFT treats both axes alike
    assert s_v.min() > s_f.max() * 10


def test_split_gaussians_moment_matches_the_parent() -> None:
    g = random_gaussians(10, sh_degree=2, seed=2, scale_range=(0.02, 0.2))
    mask = torch.zeros(10, dtype=torch.bool)
    mask[[1, 4, 7]] = True
    out = split_gaussians(g, mask)
    assert len(out) == 10 - 3 + 6
    a, b, parents = out[7:10], out[10:13], g[mask]
    # The pair keeps the parent's mean and covariance.
    assert torch.allclose((a.means + b.means) / 2, parents.means, atol=1e-6)

    def cov(x: Gaussians) -> torch.Tensor:
        w, i, j, k = x.rotations.unbind(1)
        r = torch.stack([1 - 2 * (j * j + k * k), 2 * (i * j - w * k), 2 * (i * k + w * j),
                         2 * (i * j + w * k), 1 - 2 * (i * i + k * k), 2 * (j * k - w * i),
                         2 * (i * k - w * j), 2 * (j * k + w * i), 1 - 2 * (i * i + j * j)], 1).view(-1, 3, 3)
        return r @ torch.diag_embed(x.scales ** 2) @ r.transpose(1, 2)

    d = a.means - parents.means
    mixture = cov(a) + d.unsqueeze(2) * d.unsqueeze(1)
    assert torch.allclose(mixture, cov(parents), atol=1e-6)
    assert torch.equal(a.sh, parents.sh) and torch.equal(b.quats, parents.quats)
    # Two coincident children would composite to the parent's opacity (the default rule).
    assert torch.allclose(1 - (1 - a.opacities) ** 2, parents.opacities, atol=1e-5)
    # Renders change little (unlike 3DGS' random split).
    cam = _cams(1, 64)[0]
    diff = (rasterize(out, cam).image - rasterize(g, cam).image).abs().mean()
    assert diff < 0.02


def test_footprint_rule_keeps_a_faint_parents_footprint() -> None:
    # one faint, elongated Gaussian seen face-on: the footprint rule's pair renders closer to it than the default's
    g = Gaussians(means=torch.zeros(1, 3), log_scales=torch.log(torch.tensor([[0.3, 0.08, 0.08]])),
                  quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]), opacity_logits=torch.logit(torch.tensor([0.05])),
                  sh=torch.full((1, 1, 3), 1.0))
    cam = Camera.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 0.9, 64, 64)
    mask = torch.ones(1, dtype=torch.bool)
    ref = rasterize(g, cam).image
    err = {rule: float((rasterize(split_gaussians(g, mask, rule), cam).image - ref).abs().sum() / ref.sum())
           for rule in ("coincident", "footprint")}
    assert err["footprint"] < 0.5 * err["coincident"] and err["coincident"] > 0.05
    faint = split_gaussians(g, mask, "footprint").opacities
    assert torch.allclose(faint, torch.full((2,), 1 - 0.95 ** (1 / math.sqrt(3))), atol=1e-6)
    with pytest.raises(ValueError, match="opacity_rule"):
        split_gaussians(g, mask, "mass")


def test_fgd_split_selects_candidates_and_is_deterministic() -> None:
    cams = _cams(2, 64)
    g = random_gaussians(300, sh_degree=1, seed=3, extent=0.6, scale_range=(0.01, 0.08))
    out1, rep1 = fgd_split(g, cams, top_percent=10.0)
    out2, rep2 = fgd_split(g, cams, top_percent=10.0)
    assert rep1.num_candidates > 0 and 0 < rep1.num_split <= rep1.num_candidates
    assert len(out1) == 300 + rep1.num_split
    assert torch.equal(out1.means, out2.means)
    assert rep1.patches_per_view == [round(16 * 0.1)] * 2
    with pytest.raises(ValueError, match="top_percent"):
        fgd_split(g, cams, top_percent=0.0)
