"""gsw.plots: a clear error without matplotlib; the figures of a tiny grid when it is installed."""

from __future__ import annotations

import sys

import pytest

from gsw.data import read_image
from gsw.eval.grid import GridSpec, default_grid_scene, lpips_loss_overrides, run_grid
from gsw.eval.plots import plot_grid, require_matplotlib


def test_missing_matplotlib_names_the_install_command(monkeypatch, tmp_path) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    with pytest.raises(ImportError, match=r"pip install matplotlib"):
        require_matplotlib()
    with pytest.raises(ImportError, match=r"gsw\[plots\]"):
        plot_grid(tmp_path)  # fails before reading anything


@pytest.mark.parametrize("sweeps", [("noise", "rotation"), ()])
def test_plots_of_a_tiny_grid(tmp_path, sweeps) -> None:
    pytest.importorskip("matplotlib")
    spec = GridSpec(methods=("3d-gsw", "no-mask"), bits=(32,), seeds=(0,), epochs=1, image_attacks=(),
                    model_attacks=(), sweeps=sweeps, embed=lpips_loss_overrides(None),
                    lpips_net=None)
    run_grid(spec, default_grid_scene(size=32, views=2, eval_views=1, detail=0.2), tmp_path, progress=False)
    written = plot_grid(tmp_path)
    names = ["robustness.png", "difference_maps.png"] if sweeps else ["difference_maps.png"]
    assert [p.name for p in written] == names
    for path in written:
        image = read_image(path)
        assert image.shape[0] in (3, 4) and min(image.shape[1:]) > 100
