"""Tests for gsw.gaussians."""

from __future__ import annotations

import pytest
import torch

from gsw.gaussians import (
    Gaussians,
    cat_gaussians,
    num_coeffs_to_sh_degree,
    rgb_to_sh_dc,
    sh_dc_to_rgb,
    sh_degree_to_num_coeffs,
)


def make(n: int = 5, degree: int = 3, dtype: torch.dtype = torch.float32, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return Gaussians(
        means=torch.randn(n, 3, generator=g, dtype=dtype),
        log_scales=torch.randn(n, 3, generator=g, dtype=dtype),
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        opacity_logits=torch.randn(n, generator=g, dtype=dtype),
        sh=torch.randn(n, k, 3, generator=g, dtype=dtype),
    )


def assert_same(a: Gaussians, b: Gaussians) -> None:
    for name, t in a.parameters().items():
        assert torch.equal(t, b.parameters()[name]), name


def test_properties():
    g = make(7, degree=2)
    assert len(g) == g.num_gaussians == 7
    assert g.sh_degree == 2
    assert g.dtype == torch.float32 and g.device == torch.device("cpu")
    torch.testing.assert_close(g.scales, g.log_scales.exp())
    torch.testing.assert_close(g.opacities, torch.sigmoid(g.opacity_logits))
    torch.testing.assert_close(g.rotations.norm(dim=1), torch.ones(7))
    torch.testing.assert_close(g.rotations, g.quats / g.quats.norm(dim=1, keepdim=True))
    assert list(g.parameters()) == ["means", "log_scales", "quats", "opacity_logits", "sh"]
    assert "N=7" in repr(g)


def test_sh_degree_helpers():
    assert [sh_degree_to_num_coeffs(d) for d in range(4)] == [1, 4, 9, 16]
    assert [num_coeffs_to_sh_degree(k) for k in (1, 4, 9, 16)] == [0, 1, 2, 3]
    with pytest.raises(ValueError):
        sh_degree_to_num_coeffs(4)
    with pytest.raises(ValueError):
        num_coeffs_to_sh_degree(5)


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("means", torch.zeros(5, 2), "means"),
        ("log_scales", torch.zeros(4, 3), "log_scales"),
        ("quats", torch.zeros(5, 3), "quats"),
        ("opacity_logits", torch.zeros(5, 1), "opacity_logits"),
        ("sh", torch.zeros(5, 5, 3), "sh"),
        ("sh", torch.zeros(5, 4, 1), "sh"),
        ("sh", torch.zeros(5, 4, 3, dtype=torch.float64), "sh.*dtype"),
        ("quats", torch.zeros(5, 4, dtype=torch.int64), "quats.*floating"),
        ("means", [[0.0, 0.0, 0.0]], "means.*Tensor"),
    ],
)
def test_validation_names_the_field(field, value, match):
    params = make(5, degree=1).parameters()
    params[field] = value
    with pytest.raises(ValueError, match=match):
        Gaussians(**params)


def test_empty():
    g = Gaussians.empty(2, dtype=torch.float64)
    assert len(g) == 0 and g.sh_degree == 2 and g.dtype == torch.float64
    assert g.sh.shape == (0, 9, 3)


def test_indexing():
    g = make(6)
    one = g[2]
    assert len(one) == 1 and torch.equal(one.means[0], g.means[2])
    assert torch.equal(g[-1].sh[0], g.sh[5])
    assert_same(g[1:4], Gaussians(*(t[1:4] for t in g.parameters().values())))
    mask = torch.tensor([True, False, True, False, False, True])
    assert torch.equal(g[mask].opacity_logits, g.opacity_logits[mask])
    idx = torch.tensor([5, 0, 0])
    assert torch.equal(g[idx].quats, g.quats[idx])
    assert torch.equal(g[[3, 1]].log_scales, g.log_scales[[3, 1]])
    with pytest.raises(IndexError):
        g[6]
    with pytest.raises(IndexError):
        g[torch.ones(3, dtype=torch.bool)]
    with pytest.raises(IndexError):
        g[torch.zeros(2, dtype=torch.float32)]


def test_cat_promotes_sh_degree():
    a, b = make(3, degree=3, seed=1), make(2, degree=1, seed=2)
    c = cat_gaussians([a, b])
    assert len(c) == 5 and c.sh_degree == 3
    assert torch.equal(c.sh[:3], a.sh)
    assert torch.equal(c.sh[3:, :4], b.sh)
    assert torch.count_nonzero(c.sh[3:, 4:]) == 0
    assert_same(Gaussians.cat([a, b]), c)
    with pytest.raises(ValueError):
        cat_gaussians([])
    with pytest.raises(ValueError, match="float64"):
        cat_gaussians([a, make(2, dtype=torch.float64)])


def test_with_sh_degree():
    g = make(4, degree=2)
    low = g.with_sh_degree(0)
    assert low.sh.shape == (4, 1, 3) and torch.equal(low.sh[:, 0], g.sh[:, 0])
    high = g.with_sh_degree(3)
    assert high.sh.shape == (4, 16, 3)
    assert torch.equal(high.sh[:, :9], g.sh) and torch.count_nonzero(high.sh[:, 9:]) == 0
    assert high.means is g.means
    with pytest.raises(ValueError):
        g.with_sh_degree(4)


def test_check_finite_names_field_and_rows():
    g = make(5)
    assert g.check_finite() is g
    g.sh[1, 3, 0] = float("nan")
    g.sh[1, 4, 2] = float("inf")
    g.sh[3, 0, 0] = float("-inf")
    g.opacity_logits[0] = float("nan")
    with pytest.raises(ValueError) as info:
        g.check_finite()
    msg = str(info.value)
    assert "sh: 2 of 5 rows" in msg
    assert "opacity_logits: 1 of 5 rows" in msg
    assert "means" not in msg


def test_to_clone_detach_requires_grad():
    g = make(3)
    d = g.to(dtype=torch.float64)
    assert d.dtype == torch.float64 and torch.equal(d.means.float(), g.means)
    c = g.clone()
    c.means.add_(1.0)
    assert not torch.equal(c.means, g.means)
    assert g.requires_grad_() is g
    assert all(t.requires_grad for t in g.parameters().values())
    loss = g.scales.sum() + g.opacities.sum() + g.rotations.sum() + g.sh.sum() + g.means.sum()
    loss.backward()
    assert all(t.grad is not None for t in g.parameters().values())
    det = g.detach()
    assert not any(t.requires_grad for t in det.parameters().values())
    assert det.means.data_ptr() == g.means.data_ptr()
    g.requires_grad_(False)
    assert not g.means.requires_grad


def test_rgb_sh_dc_conversion_pair():
    """rgb = 0.5 + C0 f_dc with C0 = 1 / (2 sqrt(pi)), the degree-0 SH basis constant (INRIA convention)."""
    c0 = 0.5 / torch.pi**0.5
    f_dc = torch.tensor([[0.0, 1.0, -2.0]], dtype=torch.float64)
    torch.testing.assert_close(sh_dc_to_rgb(f_dc), 0.5 + c0 * f_dc, rtol=0, atol=1e-15)
    rgb = torch.rand(10, 3, dtype=torch.float64)
    torch.testing.assert_close(sh_dc_to_rgb(rgb_to_sh_dc(rgb)), rgb, rtol=0, atol=1e-15)
    assert rgb_to_sh_dc(torch.full((3,), 0.5)).abs().max() == 0  # mid grey is f_dc = 0
    assert sh_dc_to_rgb(torch.zeros(2, 3, dtype=torch.float16)).dtype == torch.float16



def test_quaternion_matrix_round_trip():
    from gsw.gaussians import quat_to_rotmat, rotmat_to_quat
    from gsw.render._reference.project import _quat_to_rotmat

    q = torch.nn.functional.normalize(torch.randn(2000, 4, dtype=torch.float64), dim=1)
    half_turns = torch.tensor([[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0.6, 0.8, 0], [1, 0, 0, 0.0]],
                              dtype=torch.float64)  # trace -1 (and identity): the hard cases
    q = torch.cat([q, half_turns])
    r = quat_to_rotmat(q)
    torch.testing.assert_close(r, _quat_to_rotmat(q))
    torch.testing.assert_close(r @ r.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(len(q), 3, 3))
    back = rotmat_to_quat(r)
    assert (back[:, 0] >= 0).all()
    torch.testing.assert_close(back, torch.where(q[:, :1] < 0, -q, q), atol=1e-12, rtol=0)
    assert rotmat_to_quat(r[:2000].reshape(20, 100, 3, 3)).shape == (20, 100, 4)
    torch.testing.assert_close(quat_to_rotmat(3 * q[:4]), r[:4])  # unnormalised input
