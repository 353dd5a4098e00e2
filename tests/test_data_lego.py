"""The real NeRF-synthetic lego scene in ../shared/data (skipped when absent, a failure on CI)."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import SHARED_DATA, require
import torch

from gsw.data.loaders import detect_format, holdout_indices, load_dataset, load_nerf_synthetic

LEGO = SHARED_DATA / "lego"


@pytest.fixture(scope="module")
def lego_root() -> Path:
    require(LEGO / "transforms_train.json", "shared data")
    return LEGO


def test_lego_holdout_split(lego_root):
    test = load_nerf_synthetic(lego_root, "test", downscale=8)
    assert len(test) == 13 and test.images.shape == (13, 3, 100, 100)
    assert test.names[:3] == ["./train/r_0", "./train/r_8", "./train/r_16"]
    assert test.alphas is not None and float(test.images.min()) >= 0 and float(test.images.max()) <= 1
    assert detect_format(lego_root) == "nerf_synthetic"
    train_idx, test_idx = holdout_indices(100, 8)
    assert len(train_idx) == 87 and test_idx == list(range(0, 100, 8))
    assert len(load_dataset(lego_root, "val", downscale=16)) == 13  # no val file either: the same hold-out


def test_lego_cameras_look_at_the_model(lego_root):
    """The object sits at the world origin: it projects near the image centre, in front of every camera, and the
    alpha mask is opaque there."""
    ds = load_nerf_synthetic(lego_root, "test", downscale=8)
    for cam, alpha in zip(ds.cameras, ds.alphas):
        uv, depth = cam.project(torch.zeros(1, 3, dtype=torch.float64))
        assert 3.0 < float(depth) < 5.0
        assert abs(float(uv[0, 0]) - 50) < 5 and abs(float(uv[0, 1]) - 50) < 5
        assert float(alpha[0, 40:60, 40:60].mean()) > 0.5  # the lego covers the centre
        assert float(alpha[0, :3, :].mean()) < 0.05  # empty border
