"""Tests for gsw.data.colmap_io / gsw.data.colmap (COLMAP sparse models), against pycolmap (a test-only
dependency: these tests skip without it, and fail under CI)."""

from __future__ import annotations

import json
import math
import os
import struct

import numpy as np
import pytest
import torch
from helpers import SHARED_DATA, require

from gsw.camera import Camera
from gsw.data import (DatasetError, camera_to_colmap, colmap_cameras, detect_format, load_colmap, load_dataset,
                      read_colmap_model, undistort_pixels, write_colmap_model, write_image)
from gsw.data.colmap import colmap_camera
from gsw.data.colmap_io import ColmapCamera, ColmapError, ColmapImage, ColmapModel

LEGO = SHARED_DATA / "lego"


def pycolmap():
    try:
        import pycolmap as module
    except ImportError:
        if os.environ.get("CI"):
            pytest.fail("pycolmap is required by the COLMAP tests under CI")
        pytest.skip("pycolmap not installed")
    return module


def lego_cameras() -> list[Camera]:
    meta = json.loads(require(LEGO / "transforms_train.json", "shared data").read_text())
    return [Camera.from_nerf(torch.tensor(f["transform_matrix"]), 800, 800, fov_x=meta["camera_angle_x"],
                             name=f"{f['file_path'].split('/')[-1]}.png") for f in meta["frames"]]


def pycolmap_reconstruction(cameras: list[Camera], model: str = "PINHOLE", extra: tuple = ()):
    pc = pycolmap()
    rec = pc.Reconstruction()
    c0 = cameras[0]
    cam = pc.Camera.create_from_model_name(1, model, c0.fx, c0.width, c0.height)
    base = {"SIMPLE_PINHOLE": [c0.fx, c0.cx, c0.cy], "SIMPLE_RADIAL": [c0.fx, c0.cx, c0.cy],
            "RADIAL": [c0.fx, c0.cx, c0.cy]}.get(model, [c0.fx, c0.fy, c0.cx, c0.cy])
    cam.params = base + list(extra)
    rec.add_camera_with_trivial_rig(cam)
    for i, c in enumerate(cameras, 1):
        image = pc.Image(name=c.name, camera_id=1, image_id=i)
        rec.add_image_with_trivial_frame(image, pc.Rigid3d(c.viewmat.double().numpy()[:3, :4]))
    rec.add_point3D(np.array([0.1, -0.2, 0.3]), pc.Track(), np.array([10, 200, 30], dtype=np.uint8))
    return rec


def assert_same_cameras(loaded: list[Camera], expected: list[Camera]) -> None:
    by_name = {c.name: c for c in expected}
    assert sorted(c.name for c in loaded) == sorted(by_name)
    for cam in loaded:
        ref = by_name[cam.name]
        assert (cam.viewmat.double() - ref.viewmat.double()).abs().max() <= 1e-6
        assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == pytest.approx(
            (ref.fx, ref.fy, ref.cx, ref.cy, ref.width, ref.height), abs=1e-9)


def test_binary_model_written_by_pycolmap(tmp_path):
    cams = lego_cameras()
    pycolmap_reconstruction(cams).write_binary(str(tmp_path))
    model = read_colmap_model(tmp_path)
    assert [c.model for c in model.cameras.values()] == ["PINHOLE"] and len(model.images) == 100
    loaded = [c for c, d in colmap_cameras(model)]
    assert all(d.is_identity for _, d in colmap_cameras(model))
    assert [c.name for c in loaded] == sorted(c.name for c in cams)  # name order, like INRIA
    assert_same_cameras(loaded, cams)
    np.testing.assert_allclose(model.points, [[0.1, -0.2, 0.3]])
    assert model.colors.tolist() == [[10, 200, 30]]


@pytest.mark.parametrize("binary", [False, True])
def test_own_writer_matches_pycolmap(tmp_path, binary):
    cams = lego_cameras()
    entries = [camera_to_colmap(c, image_id=i + 1, camera_id=i + 1) for i, c in enumerate(cams)]
    model = ColmapModel({cam.camera_id: cam for _, cam in entries}, [im for im, _ in entries],
                        np.array([[1.0, 2.0, 3.0]]), np.array([[1, 2, 3]], dtype=np.uint8))
    write_colmap_model(tmp_path, model, binary=binary)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        f"{n}.{'bin' if binary else 'txt'}" for n in ("cameras", "images", "points3D"))
    assert_same_cameras([c for c, _ in colmap_cameras(read_colmap_model(tmp_path))], cams)
    rec = pycolmap().Reconstruction()
    (rec.read_binary if binary else rec.read_text)(str(tmp_path))
    assert rec.num_images() == 100 and rec.num_points3D() == 1
    for image in rec.images.values():
        ref = next(c for c in cams if c.name == image.name)
        np.testing.assert_allclose(image.cam_from_world().matrix(), ref.viewmat.double().numpy()[:3], atol=1e-6)
        cam = rec.cameras[image.camera_id]
        assert cam.model_name == "PINHOLE"
        np.testing.assert_allclose(cam.params, [ref.fx, ref.fy, ref.cx, ref.cy])


def test_camera_models_match_pycolmap_undistortion():
    """Each supported model's parameters map onto gsw's OpenCV distortion exactly like COLMAP's unprojection."""
    pc = pycolmap()
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [640, 480], size=(200, 2))
    for model, params in {"SIMPLE_PINHOLE": [500, 320.5, 240.2], "PINHOLE": [500, 520, 320.5, 240.2],
                          "SIMPLE_RADIAL": [500, 320.5, 240.2, -0.12], "RADIAL": [500, 320.5, 240.2, -0.12, 0.03],
                          "OPENCV": [500, 520, 320.5, 240.2, -0.12, 0.03, 0.002, -0.001]}.items():
        ref = pc.Camera.create_from_model_name(1, model, 500.0, 640, 480)
        ref.params = params
        cam, dist = colmap_camera(ColmapImage(1, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, "a.png"),
                                  ColmapCamera(1, model, 640, 480, tuple(params)))
        expected = ref.cam_from_img(uv) * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        ours = undistort_pixels(torch.from_numpy(uv), cam.fx, cam.fy, cam.cx, cam.cy, dist).numpy()
        assert np.abs(ours - expected).max() <= 1e-3, model
        assert dist.is_identity == (model in ("SIMPLE_PINHOLE", "PINHOLE"))


def blobs(height: int, width: int, centres: np.ndarray, sigma: float = 1.2) -> torch.Tensor:
    """[3, H, W] image of white Gaussian dots on black at pixel coordinates ``centres`` [K, 2] (edge convention)."""
    jj, ii = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    img = np.zeros((height, width))
    for u, v in centres:
        img += np.exp(-((ii - u) ** 2 + (jj - v) ** 2) / (2 * sigma ** 2))
    return torch.from_numpy(np.clip(img, 0, 1)).float().expand(3, -1, -1).clone()


def centroids(image: torch.Tensor, around: np.ndarray, radius: int = 5) -> np.ndarray:
    gray = image.mean(0).double().numpy()
    out = []
    for u, v in around:
        i0, j0 = int(u) - radius, int(v) - radius
        patch = gray[j0 : j0 + 2 * radius + 1, i0 : i0 + 2 * radius + 1]
        jj, ii = np.mgrid[j0 : j0 + 2 * radius + 1, i0 : i0 + 2 * radius + 1] + 0.5
        out.append([(patch * ii).sum() / patch.sum(), (patch * jj).sum() / patch.sum()])
    return np.array(out)


def test_opencv_camera_undistorts_the_image_like_pycolmap(tmp_path):
    """Dots drawn where pycolmap's OPENCV model puts ideal pixels land back on them after gsw's undistortion."""
    pc = pycolmap()
    w, h = 160, 120
    params = [110.0, 108.0, 80.3, 59.6, -0.25, 0.06, 0.004, -0.003]
    ref = pc.Camera.create_from_model_name(1, "OPENCV", 110.0, w, h)
    ref.params = params
    ideal = np.array([(u, v) for u in np.linspace(15, w - 15, 6) for v in np.linspace(15, h - 15, 5)])
    normalised = (ideal - params[2:4]) / params[:2]
    distorted = ref.img_from_cam(np.concatenate([normalised, np.ones((len(ideal), 1))], axis=1))
    assert np.abs(distorted - ideal).max() > 3  # the lens moves the outer dots by several pixels
    (tmp_path / "images").mkdir()
    write_image(tmp_path / "images" / "dots.png", blobs(h, w, distorted))
    model = ColmapModel({1: ColmapCamera(1, "OPENCV", w, h, tuple(params))},
                        [ColmapImage(1, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 1, "dots.png")],
                        np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8))
    write_colmap_model(tmp_path / "sparse" / "0", model)
    ds = load_colmap(tmp_path, "all")
    cam = ds.cameras[0]
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == tuple(params[:4])
    found = centroids(ds.images[0], ideal)
    assert np.abs(found - ideal).max() <= 0.5
    with pytest.raises(DatasetError, match="undistort=False"):
        load_colmap(tmp_path, "all", undistort=False)


def write_scene(root, cameras: list[Camera], *, folders: dict[str, int]) -> None:
    """A COLMAP scene with random images: ``folders`` maps images / images_N to the size divisor."""
    entries = [camera_to_colmap(c, image_id=i + 1, camera_id=1) for i, c in enumerate(cameras)]
    model = ColmapModel({1: entries[0][1]}, [im for im, _ in entries], np.random.default_rng(0).normal(size=(5, 3)),
                        np.full((5, 3), 255, dtype=np.uint8))
    write_colmap_model(root / "sparse" / "0", model, binary=False)
    gen = torch.Generator().manual_seed(0)
    for folder, factor in folders.items():
        (root / folder).mkdir(parents=True)
        for c in cameras:
            write_image(root / folder / c.name, torch.rand(3, c.height // factor, c.width // factor, generator=gen))


def test_dataset_splits_downscaled_folders_and_detection(tmp_path):
    cams = [Camera.look_at((math.cos(a) * 4, math.sin(a) * 4, 1), (0, 0, 0), (0, 0, 1), 0.9, 64, 48,
                           name=f"img_{k:02d}.png") for k, a in enumerate(np.linspace(0, 6, 10))]
    write_scene(tmp_path, cams, folders={"images": 1, "images_2": 2})
    assert detect_format(tmp_path) == "colmap"
    ds = load_dataset(tmp_path, "all")
    assert ds.format == "colmap" and ds.images.shape == (10, 3, 48, 64) and ds.alphas is None
    assert_same_cameras(ds.cameras, cams)
    assert ds.points.shape == (5, 3) and torch.equal(ds.point_colors, torch.ones(5, 3))
    train, test = load_colmap(tmp_path, "train"), load_colmap(tmp_path, "test")
    assert test.names == ["img_00.png", "img_08.png"] and len(train) == 8
    half = load_colmap(tmp_path, "all", downscale=2)  # reads images_2, intrinsics follow the files' size
    assert half.meta["images_dir"].endswith("images_2") and half.images.shape == (10, 3, 24, 32)
    assert half.cameras[0].fx == pytest.approx(cams[0].fx / 2) and half.cameras[0].cx == pytest.approx(16)
    third = load_colmap(tmp_path, "all", downscale=4)  # no images_4: images/ resized
    assert third.meta["images_dir"].endswith("images") and third.images.shape == (10, 3, 12, 16)
    (tmp_path / "images" / "img_03.png").unlink()
    with pytest.raises(DatasetError, match="image not found"):
        load_colmap(tmp_path, "all")


def test_rejects_bad_models(tmp_path):
    model = ColmapModel({1: ColmapCamera(1, "OPENCV_FISHEYE", 10, 10, (1.0,) * 8)},
                        [ColmapImage(1, (1.0, 0, 0, 0), (0.0, 0, 0), 1, "a.png")], np.zeros((0, 3)),
                        np.zeros((0, 3), dtype=np.uint8))
    write_colmap_model(tmp_path / "fisheye", model)
    with pytest.raises(ColmapError, match="OPENCV_FISHEYE is not supported"):
        colmap_cameras(read_colmap_model(tmp_path / "fisheye"))
    (tmp_path / "fisheye" / "images").mkdir()
    with pytest.raises(DatasetError, match="OPENCV_FISHEYE"):
        load_colmap(tmp_path / "fisheye")
    model.cameras = {1: ColmapCamera(1, "PINHOLE", 10, 10, (5.0, 5.0, 5.0, 5.0))}
    model.images[0].camera_id = 2
    write_colmap_model(tmp_path / "orphan", model)
    with pytest.raises(ColmapError, match="refers to camera 2"):
        read_colmap_model(tmp_path / "orphan")
    model.images[0].camera_id = 1
    write_colmap_model(tmp_path / "cut", model)
    data = (tmp_path / "cut" / "images.bin").read_bytes()
    (tmp_path / "cut" / "images.bin").write_bytes(data[:-3])
    with pytest.raises(ColmapError, match="truncated"):
        read_colmap_model(tmp_path / "cut")
    (tmp_path / "cut" / "images.bin").write_bytes(data + b"\0")
    with pytest.raises(ColmapError, match="unexpected bytes"):
        read_colmap_model(tmp_path / "cut")
    cams = (tmp_path / "cut" / "cameras.bin").read_bytes()
    (tmp_path / "cut" / "cameras.bin").write_bytes(cams[:12] + struct.pack("<i", 99) + cams[16:])
    with pytest.raises(ColmapError, match="unknown model id 99"):
        read_colmap_model(tmp_path / "cut")
    write_colmap_model(tmp_path / "text", model, binary=False)
    (tmp_path / "text" / "cameras.txt").write_text("1 PINHOLE 10 10 5 5 5\n")
    with pytest.raises(ColmapError, match="PINHOLE has 4 parameters, found 3"):
        read_colmap_model(tmp_path / "text")
    (tmp_path / "text" / "cameras.txt").write_text("1 PINHOLE 10 ten 5 5 5 5\n")
    with pytest.raises(ColmapError, match="cameras.txt:1: malformed camera line"):
        read_colmap_model(tmp_path / "text")
    with pytest.raises(ColmapError, match="missing file"):
        read_colmap_model(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"unknown dataset format .*COLMAP.*LLFF"):
        detect_format(tmp_path / "empty")
