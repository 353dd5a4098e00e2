"""Dataset loaders: NeRF-synthetic, instant-ngp and INRIA model folders (camera conventions, round trips,
errors)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from gsw.camera import Camera
from gsw.data.images import read_image, write_image
from gsw.data.loaders import (
    DatasetError,
    detect_format,
    load_dataset,
    load_inria_model,
    load_instant_ngp,
    load_nerf_synthetic,
    save_inria_model,
)
from gsw.io.ply import PlyError
from gsw.scenes import random_gaussians

W, H = 64, 48  # non-square on purpose: catches transposed images / focal lengths


def _gl_c2w(eye, target, up=(0.0, 0.0, 1.0)) -> list[list[float]]:
    """Blender/OpenGL camera-to-world (x right, y up, z backward), written independently of gsw.camera."""
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    back = eye - target
    back = back / back.norm()
    right = torch.linalg.cross(up, back)
    right = right / right.norm()
    true_up = torch.linalg.cross(back, right)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, back, eye
    return m.tolist()


def _gl_point_for_pixel(c2w, u, v, depth, fx, fy, cx, cy) -> torch.Tensor:
    """World point that an OpenGL camera images at pixel coordinates (u, v) (image-edge convention)."""
    m = torch.tensor(c2w, dtype=torch.float64)
    x = (u - cx) / fx * depth
    y = -(v - cy) / fy * depth  # OpenGL y is up, image v is down
    p_cam = torch.tensor([x, y, -depth, 1.0], dtype=torch.float64)  # OpenGL looks down -z
    return (m @ p_cam)[:3]


def _marker_image(col: int, row: int, *, rgba: bool = True, w: int = W, h: int = H) -> torch.Tensor:
    img = torch.zeros(4 if rgba else 3, h, w)
    img[:3, row, col] = 1.0
    if rgba:
        img[3] = 0.25
        img[3, row, col] = 1.0
    return img


def _write_nerf(root: Path, split: str, frames: list[dict], **top) -> None:
    root.mkdir(parents=True, exist_ok=True)
    (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": top.pop("angle", 1.0),
                                                             "frames": frames, **top}))


def _fov_for_focal(f: float, size: int) -> float:
    return 2.0 * math.atan(size / (2.0 * f))


# ------------------------------------------------------------------------------------------- NeRF-synthetic


def test_nerf_synthetic_camera_convention(tmp_path):
    """A world point lands on the marker pixel of the loaded image, through the loaded camera."""
    f = 50.0
    (tmp_path / "train").mkdir(parents=True)
    frames, points, pixels = [], [], []
    for k, (eye, col, row) in enumerate([((0.0, -4.0, 0.5), 40, 17), ((3.0, 2.0, 1.0), 9, 30)]):
        c2w = _gl_c2w(eye, (0.0, 0.0, 0.0))
        write_image(tmp_path / "train" / f"r_{k}.png", _marker_image(col, row))
        frames.append({"file_path": f"./train/r_{k}", "transform_matrix": c2w})
        points.append(_gl_point_for_pixel(c2w, col + 0.5, row + 0.5, 3.0, f, f, W / 2, H / 2))
        pixels.append((col, row))
    _write_nerf(tmp_path, "train", frames, angle=_fov_for_focal(f, W))
    ds = load_nerf_synthetic(tmp_path, "train", holdout_every=0, background=(0, 0, 0))
    assert ds.images.shape == (2, 3, H, W) and ds.alphas is not None and len(ds) == 2
    for cam, img, p, (col, row) in zip(ds.cameras, ds.images, points, pixels):
        assert (cam.width, cam.height) == (W, H) and cam.fx == pytest.approx(f) and cam.fy == pytest.approx(f)
        uv, depth = cam.project(p[None])
        assert uv[0].tolist() == pytest.approx([col + 0.5, row + 0.5], abs=1e-6)
        assert float(depth) == pytest.approx(3.0)
        flat = int(img.sum(0).argmax())
        assert (flat // W, flat % W) == (row, col)


def test_nerf_synthetic_background_and_alpha(tmp_path):
    (tmp_path / "train").mkdir(parents=True)
    img = torch.zeros(4, H, W)
    img[0] = 1.0
    img[3, :, : W // 2] = 1.0  # left half opaque red, right half transparent
    write_image(tmp_path / "train" / "a.png", img)
    _write_nerf(tmp_path, "train", [{"file_path": "train/a.png", "transform_matrix": _gl_c2w((0, -4, 0), (0, 0, 0))}])
    white = load_nerf_synthetic(tmp_path, "train", holdout_every=0)
    black = load_nerf_synthetic(tmp_path, "train", holdout_every=0, background=(0, 0, 0))
    assert torch.allclose(white.images[0, :, 0, -1], torch.ones(3))
    assert torch.allclose(black.images[0, :, 0, -1], torch.zeros(3))
    assert torch.allclose(white.images[0, :, 0, 0], torch.tensor([1.0, 0, 0]))
    assert float(white.alphas[0, 0, 0, 0]) == 1.0 and float(white.alphas[0, 0, 0, -1]) == 0.0


def test_nerf_synthetic_holdout_and_downscale(tmp_path):
    (tmp_path / "train").mkdir(parents=True)
    frames = []
    for k in range(10):
        write_image(tmp_path / "train" / f"r_{k}.png", torch.full((3, H, W), k / 10.0))
        frames.append({"file_path": f"./train/r_{k}", "transform_matrix": _gl_c2w((4.0, k - 5.0, 1.0), (0, 0, 0))})
    _write_nerf(tmp_path, "train", frames, angle=0.8)
    train = load_nerf_synthetic(tmp_path, "train")
    test = load_nerf_synthetic(tmp_path, "test")
    assert [n.split("_")[-1] for n in test.names] == ["0", "8"]
    assert len(train) == 8 and "./train/r_8" not in train.names and train.meta["holdout"]
    small = load_nerf_synthetic(tmp_path, "test", downscale=4)
    assert small.images.shape == (2, 3, H // 4, W // 4)
    cam, big = small.cameras[1], test.cameras[1]
    assert cam.fx == pytest.approx(big.fx / 4) and cam.cx == pytest.approx(W / 8)
    assert torch.allclose(small.images[1], torch.full((3, H // 4, W // 4), 0.8), atol=1 / 255)
    assert detect_format(tmp_path) == "nerf_synthetic"
    assert len(load_dataset(tmp_path, "test")) == 2


# ------------------------------------------------------------------------------------------- instant-ngp


def test_instant_ngp_camera_convention(tmp_path):
    fx, fy, cx, cy = 55.0, 60.0, 30.0, 26.0  # off-centre principal point, non-square pixels
    c2w = _gl_c2w((1.0, -4.0, 2.0), (0.2, 0.0, 0.3))
    col, row = 50, 8
    (tmp_path / "images").mkdir()
    write_image(tmp_path / "images" / "0001.png", _marker_image(col, row, rgba=False))
    meta = {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": W, "h": H, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            "aabb_scale": 16, "frames": [{"file_path": "images/0001.png", "transform_matrix": c2w}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    ds = load_instant_ngp(tmp_path)
    assert ds.meta["aabb_scale"] == 16 and ds.alphas is None
    cam = ds.cameras[0]
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (fx, fy, cx, cy)
    p = _gl_point_for_pixel(c2w, col + 0.5, row + 0.5, 2.5, fx, fy, cx, cy)
    uv, _ = cam.project(p[None])
    assert uv[0].tolist() == pytest.approx([col + 0.5, row + 0.5], abs=1e-6)
    flat = int(ds.images[0].sum(0).argmax())
    assert (flat // W, flat % W) == (row, col)
    assert detect_format(tmp_path) == "instant_ngp" and detect_format(tmp_path / "transforms.json") == "instant_ngp"
    # downscale keeps the convention (image edges map onto image edges)
    half = load_instant_ngp(tmp_path / "transforms.json", downscale=2).cameras[0]
    uv2, _ = half.project(p[None])
    assert uv2[0].tolist() == pytest.approx([(col + 0.5) / 2, (row + 0.5) / 2], abs=1e-6)


# ------------------------------------------------------------------------------------------- INRIA


def _cams() -> list[Camera]:
    cams = [Camera.look_at((3.0, -2.0, 1.0 + 0.1 * k), (0.0, 0.1 * k, 0.0), (0, 0, 1), 0.9, W, H, name=f"img_{k}")
            for k in range(3)]
    return cams


def test_inria_round_trip(tmp_path):
    g = random_gaussians(50, sh_degree=2, seed=1)
    cams = _cams()
    ply = save_inria_model(tmp_path, g, cams, 7000)
    assert ply == tmp_path / "point_cloud" / "iteration_7000" / "point_cloud.ply"
    save_inria_model(tmp_path, g[:10], cams, 30)
    model = load_inria_model(tmp_path)
    assert model.iteration == 7000 and model.images is None and len(model.gaussians) == 50
    gl, cl = model.gaussians, model.cameras
    for name, t in g.parameters().items():
        assert torch.equal(gl.parameters()[name], t.float()), name
    assert len(load_inria_model(tmp_path, iteration=30).gaussians) == 10
    for a, b in zip(cams, cl):
        assert torch.equal(a.viewmat, b.viewmat)
        assert (a.fx, a.fy, a.cx, a.cy, a.width, a.height, a.name) == (b.fx, b.fy, b.cx, b.cy, b.width, b.height,
                                                                       b.name)
    # with source images (full resolution on disk, cameras at that size -> used as is)
    (tmp_path / "imgs").mkdir()
    for k, cam in enumerate(cams):
        write_image(tmp_path / "imgs" / f"{cam.name}.png", torch.full((3, H, W), k / 4))
    model = load_inria_model(tmp_path, images_dir=tmp_path / "imgs")
    assert model.images.shape == (3, 3, H, W)
    assert torch.allclose(model.images[2], torch.full((3, H, W), 0.5), atol=1 / 255)
    assert detect_format(tmp_path) == "inria"
    ds = load_dataset(tmp_path, "all", images_dir=tmp_path / "imgs")
    assert len(ds) == 3 and ds.points.shape == (50, 3)


def test_inria_camera_convention():
    """INRIA entries: rotation = camera-to-world rows (OpenCV axes), position = centre."""
    right, down, fwd = torch.tensor([0.0, 1, 0]), torch.tensor([0.0, 0, -1]), torch.tensor([-1.0, 0, 0])
    rot = torch.stack([right, down, fwd], dim=1)  # columns = camera axes in world
    entry = {"id": 0, "img_name": "x", "width": W, "height": H, "position": [5.0, 0.0, 0.0],
             "rotation": rot.tolist(), "fx": 40.0, "fy": 42.0}
    cam = Camera.from_inria(entry)
    # a point 2 units in front, 0.5 right and 0.25 down of the axis
    p = torch.tensor([[5.0 - 2.0, 0.5, -0.25]], dtype=torch.float64)
    uv, depth = cam.project(p)
    assert uv[0].tolist() == pytest.approx([W / 2 + 40 * 0.25, H / 2 + 42 * 0.125])
    assert float(depth) == pytest.approx(2.0)
    # off-centre principal points survive via the extra cx/cy keys
    off = Camera(viewmat=cam.viewmat, fx=40.0, fy=42.0, cx=30.0, cy=20.0, width=W, height=H, name="o")
    back = Camera.from_inria(off.to_inria(3))
    assert (back.cx, back.cy) == (30.0, 20.0) and torch.allclose(back.viewmat, off.viewmat)


# ------------------------------------------------------------------------------------------- errors


def test_missing_files(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        load_nerf_synthetic(tmp_path / "nope")
    with pytest.raises(DatasetError, match="transforms_train.json"):
        load_nerf_synthetic(tmp_path)
    with pytest.raises(DatasetError, match="missing file"):
        load_instant_ngp(tmp_path)
    _write_nerf(tmp_path, "train", [{"file_path": "./train/r_0", "transform_matrix": _gl_c2w((0, -4, 0), (0, 0, 0))}])
    with pytest.raises(DatasetError, match="image not found"):
        load_nerf_synthetic(tmp_path, holdout_every=0)
    with pytest.raises(DatasetError, match="transforms_test.json"):
        load_nerf_synthetic(tmp_path, "test", holdout_every=0)
    with pytest.raises(DatasetError, match="not an INRIA model folder"):
        load_inria_model(tmp_path)


def test_inconsistent_sizes(tmp_path):
    (tmp_path / "train").mkdir()
    write_image(tmp_path / "train" / "a.png", torch.zeros(3, H, W))
    write_image(tmp_path / "train" / "b.png", torch.zeros(3, H, W + 2))
    m = _gl_c2w((0, -4, 0), (0, 0, 0))
    _write_nerf(tmp_path, "train", [{"file_path": "train/a", "transform_matrix": m},
                                    {"file_path": "train/b", "transform_matrix": m}])
    with pytest.raises(DatasetError, match="inconsistent image sizes"):
        load_nerf_synthetic(tmp_path, holdout_every=0)
    meta = {"fl_x": 50.0, "w": W + 1, "h": H, "frames": [{"file_path": "train/a.png", "transform_matrix": m}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="transforms file says"):
        load_instant_ngp(tmp_path / "transforms.json")


def test_malformed_and_unknown(tmp_path):
    (tmp_path / "transforms_train.json").write_text("{not json")
    with pytest.raises(DatasetError, match="malformed JSON"):
        load_nerf_synthetic(tmp_path)
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 1.0}))
    with pytest.raises(DatasetError, match="'frames' list"):
        load_nerf_synthetic(tmp_path)
    (tmp_path / "transforms_train.json").write_text(json.dumps({"frames": [{"file_path": "a"}]}))
    with pytest.raises(DatasetError, match="transform_matrix|image not found"):
        load_nerf_synthetic(tmp_path, holdout_every=0)
    (tmp_path / "train").mkdir()
    write_image(tmp_path / "train" / "a.png", torch.zeros(3, H, W))
    (tmp_path / "transforms_train.json").write_text(json.dumps(
        {"frames": [{"file_path": "train/a", "transform_matrix": _gl_c2w((0, -4, 0), (0, 0, 0))}]}))
    with pytest.raises(DatasetError, match="no focal length"):
        load_nerf_synthetic(tmp_path, holdout_every=0)
    (tmp_path / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 1.0, "frames": [{"file_path": "train/a", "transform_matrix": [[1, 0], [0, 1]]}]}))
    with pytest.raises(DatasetError, match="4x4"):
        load_nerf_synthetic(tmp_path, holdout_every=0)
    (tmp_path / "train" / "bad.png").write_bytes(b"not a png at all")
    (tmp_path / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 1.0, "frames": [{"file_path": "train/bad.png",
                                            "transform_matrix": _gl_c2w((0, -4, 0), (0, 0, 0))}]}))
    with pytest.raises(DatasetError, match="decode"):
        load_nerf_synthetic(tmp_path, holdout_every=0)
    other = tmp_path / "other"
    other.mkdir()
    (other / "readme.txt").write_text("hi")
    with pytest.raises(DatasetError, match="unknown dataset format"):
        load_dataset(other)
    with pytest.raises(DatasetError, match="unknown dataset format"):
        detect_format(other / "readme.txt")
    with pytest.raises(DatasetError, match="not found"):
        load_dataset(tmp_path / "missing")
    with pytest.raises(ValueError, match="downscale"):
        load_nerf_synthetic(tmp_path, downscale=0.5)
    with pytest.raises(ValueError, match="split"):
        load_nerf_synthetic(tmp_path, "validation")


def test_inria_errors(tmp_path):
    g = random_gaussians(5, seed=0)
    save_inria_model(tmp_path, g, _cams(), 10)
    with pytest.raises(DatasetError, match="no iteration 20"):
        load_inria_model(tmp_path, iteration=20)
    with pytest.raises(DatasetError, match="images folder not found"):
        load_inria_model(tmp_path, images_dir=tmp_path / "nope")
    (tmp_path / "imgs").mkdir()
    with pytest.raises(DatasetError, match="3 images not found: .*img_0, .*img_1, .*img_2"):
        load_inria_model(tmp_path, images_dir=tmp_path / "imgs")
    with pytest.raises(DatasetError, match="images_dir"):
        load_dataset(tmp_path)
    (tmp_path / "cameras.json").write_text(json.dumps([{"id": 0, "width": 4}]))
    with pytest.raises(DatasetError, match="lacks"):
        load_inria_model(tmp_path)
    (tmp_path / "cameras.json").write_text("[")
    with pytest.raises(DatasetError, match="malformed JSON"):
        load_inria_model(tmp_path)
    (tmp_path / "cameras.json").unlink()
    with pytest.raises(DatasetError, match="missing file"):
        load_inria_model(tmp_path)
    (tmp_path / "point_cloud" / "iteration_10" / "point_cloud.ply").write_bytes(b"garbage")
    with pytest.raises(PlyError):
        load_inria_model(tmp_path)


def test_read_image_formats(tmp_path):
    rgba = torch.rand(4, 5, 7)
    write_image(tmp_path / "x.png", rgba)
    back = read_image(tmp_path / "x.png")
    assert back.shape == (4, 5, 7) and torch.allclose(back, rgba, atol=0.5 / 255 + 1e-6)
    with pytest.raises(FileNotFoundError):
        read_image(tmp_path / "y.png")


# ------------------------------------------------------------------------------------------- strict inputs


def _nerf_scene(root: Path, n: int = 3, size: tuple[int, int] = (W, H), **top) -> list[dict]:
    (root / "train").mkdir(parents=True, exist_ok=True)
    frames = []
    for k in range(n):
        write_image(root / "train" / f"r_{k}.png", torch.full((3, size[1], size[0]), k / 4))
        frames.append({"file_path": f"./train/r_{k}", "transform_matrix": _gl_c2w((4.0, k - 1.0, 1.0), (0, 0, 0))})
    _write_nerf(root, "train", frames, **top)
    return frames


def test_missing_images_are_all_named(tmp_path):
    _nerf_scene(tmp_path, 4)
    (tmp_path / "train" / "r_1.png").unlink()
    (tmp_path / "train" / "r_3.png").unlink()
    with pytest.raises(DatasetError, match=r"transforms_train.json: 2 images not found: .*r_1, .*r_3 "):
        load_nerf_synthetic(tmp_path, holdout_every=0)


def test_inria_image_size_must_match_the_camera(tmp_path):
    cams = _cams()
    save_inria_model(tmp_path, random_gaussians(5, seed=0), cams, 10)
    (tmp_path / "imgs").mkdir()
    for k, cam in enumerate(cams):  # photos at twice the training resolution stored in cameras.json
        write_image(tmp_path / "imgs" / f"{cam.name}.png", torch.full((3, 2 * H, 2 * W), k / 4))
    with pytest.raises(DatasetError, match=rf"img_0.png: image is {2 * W}x{2 * H} but camera 0 \('img_0'\) in "
                                           rf"cameras.json is {W}x{H}; pass resize_images=True"):
        load_inria_model(tmp_path, images_dir=tmp_path / "imgs")
    model = load_inria_model(tmp_path, images_dir=tmp_path / "imgs", resize_images=True)  # the explicit opt-in
    assert model.images.shape == (3, 3, H, W)
    assert torch.allclose(model.images[2], torch.full((3, H, W), 0.5), atol=1 / 255)
    write_image(tmp_path / "imgs" / "img_1.png", torch.zeros(3, 2 * H, 3 * W))  # not a uniform multiple
    with pytest.raises(DatasetError, match=rf"img_1.png: image is {3 * W}x{2 * H}"):
        load_inria_model(tmp_path, images_dir=tmp_path / "imgs", resize_images=True)
    for cam in cams:  # images at the camera size: the explicit downscale resizes both
        write_image(tmp_path / "imgs" / f"{cam.name}.png", torch.full((3, H, W), 0.25))
    model = load_inria_model(tmp_path, images_dir=tmp_path / "imgs", downscale=2)
    assert model.images.shape == (3, 3, H // 2, W // 2) and model.cameras[0].width == W // 2
    with pytest.raises(DatasetError, match=r"a 4x3 view is too small to train on \(at least 4 pixels"):
        load_inria_model(tmp_path, images_dir=tmp_path / "imgs", downscale=16)


def test_nerf_image_size_must_match_the_transforms(tmp_path):
    _nerf_scene(tmp_path, 2, w=W, h=H)
    assert load_nerf_synthetic(tmp_path, holdout_every=0).images.shape == (2, 3, H, W)
    _nerf_scene(tmp_path, 2, w=W + 8, h=H)
    with pytest.raises(DatasetError, match=rf"frame 0: r_0.png is {W}x{H} but the transforms file says {W + 8}x{H}"):
        load_nerf_synthetic(tmp_path, holdout_every=0)


@pytest.mark.parametrize("top, frame_change, match", [
    ({"w": 64.5}, {}, r"field 'w' must be an integer, got 64.5"),
    ({"h": "48"}, {}, r"field 'h' must be an integer, got '48' \(str\)"),
    ({"w": 200000}, {}, r"field 'w' = 200000 is outside 1..16384"),
    ({"camera_angle_x": True}, {}, r"field 'camera_angle_x' must be a finite number, got True \(bool\)"),
    ({"camera_angle_x": 4.0}, {}, r"'camera_angle_x' must be in \(0, pi\)"),
    ({"fl_x": None}, {}, r"field 'fl_x' must be a positive finite number, got None"),
    ({"fl_x": -5.0}, {}, r"field 'fl_x' must be a positive finite number"),
    ({"k1": [0.1]}, {}, r"field 'k1' must be a finite number"),
    ({}, {"file_path": 3}, r"frame 1: field 'file_path' must be a non-empty string, got 3"),
    ({}, {"transform_matrix": [[True, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
     r"frame 1: field 'transform_matrix' must be a 4x4 list of finite numbers"),
    ({}, {"cx": "32"}, r"frame 1: field 'cx' must be a finite number, got '32'"),
])
def test_transforms_fields_are_type_checked(tmp_path, top, frame_change, match):
    frames = _nerf_scene(tmp_path, 2)
    frames[1].update(frame_change)
    _write_nerf(tmp_path, "train", frames, **top)
    with pytest.raises(DatasetError, match=match):
        load_nerf_synthetic(tmp_path, holdout_every=0)


def test_integral_floats_are_integers(tmp_path):
    """instant-ngp's colmap2nerf.py writes "w": 1920.0; an integral float is an integer, 64.5 is not."""
    _nerf_scene(tmp_path, 2, w=float(W), h=float(H))
    assert load_nerf_synthetic(tmp_path, holdout_every=0).cameras[0].width == W


def test_json_files_encoding_and_directories(tmp_path):
    _nerf_scene(tmp_path, 1, comment="caf\u00e9")
    path = tmp_path / "transforms_train.json"
    path.write_bytes(path.read_text().replace("\\u00e9", "\u00e9").encode("latin-1"))
    with pytest.raises(DatasetError, match=r"transforms_train.json: not UTF-8 text .*must be UTF-8"):
        load_nerf_synthetic(tmp_path, holdout_every=0)
    path.write_bytes(b"\xef\xbb\xbf" + path.read_text(encoding="latin-1").encode("utf-8"))  # BOM is fine
    assert len(load_nerf_synthetic(tmp_path, holdout_every=0)) == 1
    path.unlink()
    path.mkdir()
    with pytest.raises(DatasetError, match="transforms_train.json: is a directory, expected a JSON file"):
        load_nerf_synthetic(tmp_path, holdout_every=0)
    (tmp_path / "model" / "point_cloud" / "iteration_1").mkdir(parents=True)
    save_inria_model(tmp_path / "model", random_gaussians(3, seed=0), _cams(), 1)
    (tmp_path / "model" / "cameras.json").unlink()
    (tmp_path / "model" / "cameras.json").mkdir()
    with pytest.raises(DatasetError, match="cameras.json: is a directory"):
        load_inria_model(tmp_path / "model")


def test_tiny_and_undecodable_views(tmp_path):
    _nerf_scene(tmp_path, 2, size=(1, 1))
    with pytest.raises(DatasetError, match=r"frame 0: r_0.png: a 1x1 view is too small to train on"):
        load_nerf_synthetic(tmp_path, holdout_every=0)
    _nerf_scene(tmp_path, 2, size=(8, 8))
    assert load_nerf_synthetic(tmp_path, holdout_every=0).images.shape == (2, 3, 8, 8)
    with pytest.raises(DatasetError, match="a 2x2 view is too small"):
        load_nerf_synthetic(tmp_path, holdout_every=0, downscale=4)
    (tmp_path / "train" / "r_1.png").write_bytes(b"GIF89a not really")
    with pytest.raises(DatasetError, match="frame 1: cannot decode image .*r_1.png"):
        load_nerf_synthetic(tmp_path, holdout_every=0)


def test_inria_cameras_json_errors_name_the_camera_and_field(tmp_path):
    save_inria_model(tmp_path, random_gaussians(3, seed=0), _cams(), 1)
    entries = json.loads((tmp_path / "cameras.json").read_text())
    entries[2]["width"] = 128.9
    (tmp_path / "cameras.json").write_text(json.dumps(entries))
    with pytest.raises(DatasetError, match=r"cameras.json: camera 2: field 'width' must be an integer, got 128.9"):
        load_inria_model(tmp_path)


def test_webp_frames_are_found_without_their_extension(tmp_path):
    """NeRF-synthetic frames named without an extension may be WebP files (a compressed copy of a dataset)."""
    pytest.importorskip("PIL.WebPImagePlugin")
    from PIL import features

    if not features.check("webp"):
        pytest.skip("Pillow without WebP")
    frames = _nerf_scene(tmp_path, 3)
    for k in range(3):
        png = tmp_path / "train" / f"r_{k}.png"
        write_image(tmp_path / "train" / f"r_{k}.webp", read_image(png))
        png.unlink()
    ds = load_nerf_synthetic(tmp_path, holdout_every=0)
    assert len(ds) == len(frames) == 3
    with pytest.raises(DatasetError, match=r"also tried \.png/\.jpg/\.jpeg/\.webp"):
        (tmp_path / "train" / "r_2.webp").unlink()
        load_nerf_synthetic(tmp_path, holdout_every=0)
