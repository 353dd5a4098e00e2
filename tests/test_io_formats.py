"""Tests for gsw.io.formats (choosing readers/writers) and gsw.io.convert (conversion as a model transform)."""

from __future__ import annotations

import pytest
import torch
from helpers import random_model

from gsw.io import MODEL_FORMATS, WRITABLE_FORMATS, load_gaussians, load_model, model_format, save_gaussians, \
    save_model
from gsw.io.convert import FORMAT_SUFFIXES, ConversionCheck, check_conversion, format_round_trip, orbit_views


def test_format_by_name_and_header(tmp_path):
    g = random_model(20, degree=1)
    for fmt in WRITABLE_FORMATS:
        path = tmp_path / f"m{FORMAT_SUFFIXES[fmt]}"
        assert model_format(path, for_writing=True) == fmt
        save_gaussians(g, path)
        assert model_format(path) == fmt
        assert len(load_gaussians(path)) == 20
    save_model(g, tmp_path / "c.ply", "compressed-ply")  # a compressed file with a plain name
    assert model_format(tmp_path / "c.ply") == "compressed-ply"
    assert model_format(tmp_path / "c.ply", for_writing=True) == "ply"
    assert model_format(tmp_path / "x.ckpt") == model_format(tmp_path / "x.pt") == "checkpoint"
    assert set(WRITABLE_FORMATS) < set(MODEL_FORMATS)


def test_unknown_extensions_and_read_only_formats(tmp_path):
    g = random_model(3)
    with pytest.raises(ValueError, match=r"unknown model file extension '\.obj'; supported: .*\.spz"):
        save_gaussians(g, tmp_path / "m.obj")
    with pytest.raises(ValueError, match="cannot write 'checkpoint'"):
        save_gaussians(g, tmp_path / "m.pt")
    with pytest.raises(ValueError, match="unknown model format 'xyz'"):
        load_model(tmp_path / "m.ply", "xyz")
    assert not list(tmp_path.iterdir())
    with pytest.raises(FileNotFoundError, match="m.ply: no such model file"):
        load_gaussians(tmp_path / "m.ply")
    (tmp_path / "m.glb").write_bytes(b"glTF")
    with pytest.raises(ValueError, match="unknown model file extension"):
        load_gaussians(tmp_path / "m.glb")


@pytest.mark.parametrize("fmt", WRITABLE_FORMATS)
def test_format_round_trip(fmt):
    g = random_model(300, degree=2)
    h = format_round_trip(g, fmt)
    assert len(h) == len(g) and h.dtype == torch.float32
    assert h.sh_degree == (0 if fmt == "splat" else 2)
    if fmt == "ply":
        assert torch.equal(h.sh, g.sh)


def test_check_conversion_with_a_toy_decoder():
    """A decoder reading every bit as 1 on bright renders and 0 on dark ones: a model whose opacities are
    destroyed by the 'conversion' loses all its bits, the unchanged one keeps them."""

    class Brightness(torch.nn.Module):
        def forward(self, ll):  # noqa: D102
            return (ll.mean(dim=(1, 2, 3)) - 0.01)[:, None].expand(-1, 32)

    g = random_model(200, degree=0, seed=1)
    g = type(g)(g.means * 0.3, g.log_scales + 1.0, g.quats, g.opacity_logits.abs() + 3, g.sh.abs())
    dark = type(g)(g.means, g.log_scales, g.quats, torch.full_like(g.opacity_logits, -30.0), g.sh)
    views = orbit_views(g, n=2, size=32)
    assert len(views) == 2 and views[0].width == 32
    ones = [1] * 32
    same = check_conversion(g, g, views, ones, decoder=Brightness())
    assert same.before == same.after == [1.0, 1.0] and same.drop_points == 0 and not same.dropped()
    lost = check_conversion(g, dark, views, ones, decoder=Brightness())
    assert lost.mean_after == 0.0 and lost.drop_points == 100.0 and lost.dropped()
    assert ConversionCheck([0.9], [0.895]).dropped() is False  # 0.5 points: below the 1-point threshold
    assert ConversionCheck([0.9], [0.885]).dropped() is True
