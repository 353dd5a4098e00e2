"""Tests for gsw.data.llff (poses_bounds.npy scenes): a fixture generated from lego's cameras."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from helpers import SHARED_DATA, require

from gsw.camera import Camera
from gsw.data import DatasetError, detect_format, load_dataset, load_llff, write_image
from gsw.data.llff import llff_cameras

LEGO = SHARED_DATA / "lego"


def lego_cameras(n: int) -> list[Camera]:
    meta = json.loads(require(LEGO / "transforms_train.json", "shared data").read_text())
    return [Camera.from_nerf(torch.tensor(f["transform_matrix"]), 800, 800, fov_x=meta["camera_angle_x"])
            for f in meta["frames"][:n]]


def poses_bounds(cameras: list[Camera]) -> np.ndarray:
    """LLFF rows written independently of the loader: c2w columns (down, right, backward), centre, (H, W, f)."""
    rows = []
    for k, cam in enumerate(cameras):
        c2w = cam.c2w.double().numpy()  # OpenCV: right, down, forward
        pose = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3], [cam.height, cam.width, cam.fx]], axis=1)
        rows.append(np.concatenate([pose.reshape(-1), [2.0 + k, 6.0 + k]]))
    return np.array(rows)


def write_scene(root, cameras: list[Camera], sizes: dict[str, int]) -> None:
    np.save(root / "poses_bounds.npy", poses_bounds(cameras))
    for folder, size in sizes.items():
        (root / folder).mkdir()
        for k in range(len(cameras)):
            write_image(root / folder / f"IMG_{k:04d}.JPG", torch.full((3, size, size), k / len(cameras)))


def test_llff_scene_loads_lego_cameras(tmp_path):
    cams = lego_cameras(10)
    write_scene(tmp_path, cams, {"images": 80, "images_4": 20})
    assert detect_format(tmp_path) == "llff"
    ds = load_dataset(tmp_path, "all")
    assert ds.format == "llff" and ds.images.shape == (10, 3, 80, 80)
    assert ds.names == [f"IMG_{k:04d}.JPG" for k in range(10)]
    for got, ref in zip(ds.cameras, cams):
        assert (got.viewmat.double() - ref.viewmat.double()).abs().max() <= 1e-6
        assert got.fx == pytest.approx(ref.fx / 10) and got.cx == pytest.approx(40.0) and got.width == 80
    np.testing.assert_allclose(ds.meta["bounds"], [[2.0 + k, 6.0 + k] for k in range(10)])
    test = load_llff(tmp_path, "test", downscale=4)  # images_4: 20 x 20
    assert test.names == ["IMG_0000.JPG", "IMG_0008.JPG"] and test.images.shape == (2, 3, 20, 20)
    assert test.cameras[1].fx == pytest.approx(cams[8].fx / 40)
    np.testing.assert_allclose(test.meta["bounds"], [[2.0, 6.0], [10.0, 14.0]])


def test_rejects_bad_llff(tmp_path):
    cams = lego_cameras(3)
    with pytest.raises(DatasetError, match=r"\[N, 17\]"):
        llff_cameras(np.zeros((3, 15)))
    rows = poses_bounds(cams)
    rows[1, 0] = 5.0  # not a rotation any more
    with pytest.raises(DatasetError, match="row 1: the rotation"):
        llff_cameras(rows)
    rows = poses_bounds(cams)
    rows[2, 14] = 0.0  # focal
    with pytest.raises(DatasetError, match="row 2: bad image size"):
        llff_cameras(rows)
    write_scene(tmp_path, cams, {"images": 8})
    (tmp_path / "images" / "IMG_0001.JPG").unlink()
    with pytest.raises(DatasetError, match="2 images but poses_bounds.npy has 3 poses"):
        load_llff(tmp_path)
    (tmp_path / "poses_bounds.npy").write_bytes(b"garbage")
    with pytest.raises(DatasetError, match="not a readable .npy"):
        load_llff(tmp_path)
