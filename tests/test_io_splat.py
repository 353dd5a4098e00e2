"""Tests for gsw.io.splat (antimatter15 .splat files)."""

from __future__ import annotations


import numpy as np
import pytest
from helpers import SHARED_DATA, random_model, require
import torch

from gsw.constants import SH_C0
from gsw.io import SplatError, load_gaussians, load_ply, load_splat, save_gaussians, save_splat
from gsw.io.splat import SCALE_RANGE, SPLAT_DTYPE, splat_sort_order

DATA = SHARED_DATA
FIXTURE_DIR = DATA / "ply" / "sh3_fixture"


def same_rotation_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-row max abs difference of unit quaternions, up to the q ~ -q sign ambiguity."""
    a = torch.nn.functional.normalize(a.double(), dim=1)
    b = torch.nn.functional.normalize(b.double(), dim=1)
    return torch.minimum((a - b).abs().amax(1), (a + b).abs().amax(1))


def test_record_layout():
    assert SPLAT_DTYPE.itemsize == 32
    assert [SPLAT_DTYPE.fields[k][1] for k in ("position", "scale", "rgba", "rot")] == [0, 12, 24, 28]


def test_decoding(tmp_path):
    rec = np.zeros(2, SPLAT_DTYPE)
    rec["position"] = [[1, 2, 3], [-1, 0, 0.5]]
    rec["scale"] = [[0.1, 0.2, 0.4], [1, 1, 1]]
    rec["rgba"] = [[255, 128, 0, 255], [0, 0, 0, 0]]
    rec["rot"] = [[255, 128, 128, 128], [128, 0, 128, 128]]
    (tmp_path / "a.splat").write_bytes(rec.tobytes())
    g = load_splat(tmp_path / "a.splat")
    assert len(g) == 2 and g.sh_degree == 0 and g.dtype == torch.float32
    torch.testing.assert_close(g.means, torch.tensor(rec["position"]))
    torch.testing.assert_close(g.scales, torch.tensor(rec["scale"]))
    rgb = 0.5 + SH_C0 * g.sh[:, 0]
    torch.testing.assert_close(rgb, torch.tensor([[1.0, 128 / 255, 0.0], [0.0, 0.0, 0.0]]))
    assert torch.isfinite(g.opacity_logits).all()
    torch.testing.assert_close(g.opacities, torch.tensor([1.0, 0.0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(g.quats, torch.tensor([[127 / 128, 0, 0, 0], [0, -1, 0, 0]]))


def test_round_trip(tmp_path):
    g = random_model(500, degree=2)
    save_splat(g, tmp_path / "m.splat")
    assert (tmp_path / "m.splat").stat().st_size == 500 * 32
    h = load_splat(tmp_path / "m.splat")
    assert h.sh_degree == 0
    assert torch.equal(h.means, g.means)
    torch.testing.assert_close(h.log_scales, g.log_scales, rtol=0, atol=1e-6)
    rgb = (0.5 + SH_C0 * g.sh[:, 0]).clamp(0, 1)
    assert (0.5 + SH_C0 * h.sh[:, 0] - rgb).abs().max() <= 0.5 / 255 + 1e-6
    assert (h.opacities - g.opacities).abs().max() <= 0.5 / 255 + 1e-6
    assert same_rotation_error(h.quats, g.quats).max() <= 1.5 / 128
    # Re-encoding decoded data reproduces position, scale and colour bytes exactly.
    save_splat(h, tmp_path / "again.splat")
    a = np.fromfile(tmp_path / "m.splat", SPLAT_DTYPE)
    b = np.fromfile(tmp_path / "again.splat", SPLAT_DTYPE)
    for key in ("position", "scale", "rgba"):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert np.abs(a["rot"].astype(int) - b["rot"]).max() <= 1


def test_sorted_like_antimatter15(tmp_path):
    g = random_model(200, degree=0)
    save_splat(g, tmp_path / "s.splat", sort=True)
    h = load_splat(tmp_path / "s.splat")
    order = splat_sort_order(g)
    assert torch.equal(h.means, g.means[order])
    key = g.scales.double().prod(1) * g.opacities.double()
    assert (key[order][:-1] >= key[order][1:]).all()


def test_bad_size_empty_and_directory(tmp_path):
    (tmp_path / "bad.splat").write_bytes(b"\0" * 65)
    with pytest.raises(SplatError, match="65 bytes is not a multiple of 32"):
        load_splat(tmp_path / "bad.splat")
    (tmp_path / "empty.splat").write_bytes(b"")
    with pytest.raises(SplatError, match="empty.splat: empty file"):
        load_splat(tmp_path / "empty.splat")
    (tmp_path / "dir.splat").mkdir()
    with pytest.raises(SplatError, match="is a directory"):
        load_gaussians(tmp_path / "dir.splat")
    with pytest.raises(FileNotFoundError):
        load_splat(tmp_path / "absent.splat")


def _valid_records(n: int) -> np.ndarray:
    rec = np.zeros(n, SPLAT_DTYPE)
    rec["scale"] = 0.01
    rec["rot"] = [255, 128, 128, 128]
    return rec


@pytest.mark.parametrize("field, value, match", [
    ("position", np.nan, "non-finite position"),
    ("position", 2e7, r"position beyond \+-1e\+07"),
    ("scale", np.inf, "non-finite scale"),
    ("scale", -0.1, r"scale outside \[1e-10, 1e\+07\]"),
    ("scale", 0.0, "scale outside"),
    ("scale", 1e-30, "scale outside"),
    ("scale", 1e9, "scale outside"),
    ("rot", 128, r"zero quaternion \(rotation bytes all 128\)"),
])
def test_implausible_records_are_rejected(tmp_path, field, value, match):
    rec = _valid_records(4)
    rec[field][2] = value
    (tmp_path / "x.splat").write_bytes(rec.tobytes())
    with pytest.raises(SplatError, match=rf"x.splat: not a plausible .splat file: 1 of 4 splats have a {match}.*first: splat 2"):
        load_splat(tmp_path / "x.splat")
    rec[field][2] = _valid_records(1)[field][0]
    (tmp_path / "x.splat").write_bytes(rec.tobytes())
    assert len(load_splat(tmp_path / "x.splat")) == 4


def test_random_bytes_do_not_load(tmp_path):
    """64 random bytes decode as 2 splats; the sanity check rejects them (seeded, many draws)."""
    rng = np.random.default_rng(0)
    path = tmp_path / "r.splat"
    for _ in range(300):
        path.write_bytes(rng.bytes(64))
        with pytest.raises(SplatError, match="not a plausible .splat file"):
            load_splat(path)


def test_save_refuses_what_load_would_reject(tmp_path):
    g = random_model(3, degree=0)
    g.quats[1] = 0.0  # a zero quaternion writes rotation bytes 128
    with pytest.raises(SplatError, match="refusing to write .*zero quaternion"):
        save_splat(g, tmp_path / "z.splat")
    g = random_model(3, degree=0)
    g.log_scales[0, 0] = 40.0  # 2e17: above SCALE_RANGE
    with pytest.raises(SplatError, match="refusing to write .*scale outside"):
        save_splat(g, tmp_path / "s.splat")
    with pytest.raises(SplatError, match="0 Gaussians"):
        save_splat(random_model(0, degree=0), tmp_path / "e.splat")
    assert not any(tmp_path.iterdir())


def test_flat_splats_are_written_at_the_smallest_scale(tmp_path):
    g = random_model(3, degree=0)
    g.log_scales[0, 0] = -40.0  # 4e-18: a flat splat as 3DGS training leaves them
    save_splat(g, tmp_path / "flat.splat")
    back = load_splat(tmp_path / "flat.splat")
    assert float(back.scales[0, 0]) == pytest.approx(SCALE_RANGE[0], rel=1e-6)
    assert torch.allclose(back.scales[1:], g.scales[1:].float(), rtol=1e-6)


def test_dispatch_by_extension(tmp_path):
    g = random_model(10, degree=0)
    save_gaussians(g, tmp_path / "m.splat")
    save_gaussians(g, tmp_path / "m.ply")
    assert load_gaussians(tmp_path / "m.splat").sh_degree == 0
    assert torch.equal(load_gaussians(tmp_path / "m.ply").means, g.means)


def test_fixture_matches_ply(tmp_path):
    """model.splat is the same scene as point_cloud.ply but a different checkpoint (22,764 vs 9,080
    Gaussians, file order unrelated). Gaussians whose position is bit-identical in both files must
    agree in every attribute up to the .splat quantisation, and re-encoding them must give the same bytes."""
    ply = load_ply(require(FIXTURE_DIR / "point_cloud.ply"))
    splat_path = require(FIXTURE_DIR / "model.splat")
    splat = load_splat(splat_path)
    assert len(ply) == 9080 and len(splat) == 22764
    splat.check_finite()

    # Match by exact position bytes.
    def keys(t: torch.Tensor) -> np.ndarray:
        return np.ascontiguousarray(t.numpy()).view(np.dtype((np.void, 12))).ravel()

    _, i_ply, i_splat = np.intersect1d(keys(ply.means), keys(splat.means), return_indices=True)
    assert len(i_ply) > 2000
    p, s = ply[torch.from_numpy(i_ply)], splat[torch.from_numpy(i_splat)]
    torch.testing.assert_close(s.log_scales, p.log_scales, rtol=0, atol=1e-5)
    rgb_p = (0.5 + SH_C0 * p.sh[:, 0]).clamp(0, 1)
    rgb_s = 0.5 + SH_C0 * s.sh[:, 0]
    assert (rgb_p - rgb_s).abs().max() <= 0.5 / 255 + 1e-5
    assert (p.opacities - s.opacities).abs().max() <= 0.5 / 255 + 1e-5
    assert same_rotation_error(p.quats, s.quats).max() <= 1.0 / 128

    # Our encoder reproduces the fixture's bytes (rounding quantisation), scales up to float32 exp rounding.
    save_splat(p, tmp_path / "matched.splat")
    ours = np.fromfile(tmp_path / "matched.splat", SPLAT_DTYPE)
    theirs = np.fromfile(splat_path, SPLAT_DTYPE)[i_splat]
    for key in ("position", "rgba", "rot"):
        np.testing.assert_array_equal(ours[key], theirs[key], err_msg=key)
    np.testing.assert_allclose(ours["scale"], theirs["scale"], rtol=1e-6)

    # Whole-scene agreement: most PLY Gaussians have a splat nearby (relative to the scene size).
    extent = float((ply.means.max(0).values - ply.means.min(0).values).norm())
    nearest = torch.cat([torch.cdist(chunk, splat.means).min(1).values for chunk in ply.means.split(2048)])
    assert float(nearest.median()) < 0.01 * extent

