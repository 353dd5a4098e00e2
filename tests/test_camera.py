"""Tests for gsw.camera: conventions, constructors, round trips and validation."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from helpers import SHARED_DATA, require
import torch

from gsw.camera import (
    Camera,
    load_inria_cameras,
    orbit_cameras,
    save_inria_cameras,
    stack_Ks,
    stack_viewmats,
)

DATA = SHARED_DATA


def random_rotation(seed: int) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def pts(*rows) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64)


# ------------------------------------------------------------------------------------------ conventions


def test_from_fov_identity_projection():
    cam = Camera.from_fov(math.radians(90), 200, 100)
    assert (cam.cx, cam.cy) == (100.0, 50.0)
    assert cam.fx == pytest.approx(100.0) and cam.fy == cam.fx
    px, depth = cam.project(pts([0, 0, 5], [5, 0, 5], [0, 2, 4], [0, 0, -1]))
    torch.testing.assert_close(px[0], pts(100, 50))  # optical axis -> principal point
    assert px[1, 0].item() == pytest.approx(200.0)  # the fov edge is the image edge x = W
    assert px[2, 1].item() == pytest.approx(100.0)  # +y camera is down (larger v)
    torch.testing.assert_close(depth, pts(5, 5, 4, -1))
    assert cam.fov_x == pytest.approx(math.radians(90))
    cam2 = Camera.from_fov(1.0, 64, 48, fov_y=0.5)
    assert cam2.fov_y == pytest.approx(0.5) and cam2.fov_x == pytest.approx(1.0)


def test_project_dtype_and_formula():
    cam = Camera(viewmat=torch.eye(4), fx=10.0, fy=20.0, cx=3.0, cy=4.0, width=8, height=8)
    px, depth = cam.project(torch.tensor([[1.0, 2.0, 4.0]]))
    assert px.dtype == torch.float32
    torch.testing.assert_close(px, torch.tensor([[10 * 1 / 4 + 3.0, 20 * 2 / 4 + 4.0]]))
    assert depth.item() == 4.0


def test_from_nerf_opengl_convention():
    # Blender/NeRF: camera at (0, 0, 4) with identity rotation looks down world -z, y up.
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[2, 3] = 4.0
    cam = Camera.from_nerf(c2w, 64, 48, fov_x=math.radians(60))
    assert (cam.cx, cam.cy) == (32.0, 24.0)
    px, depth = cam.project(pts([0, 0, 0], [0, 0.5, 0], [0.5, 0, 0]))
    torch.testing.assert_close(px[0], torch.tensor([32.0, 24.0], dtype=torch.float64))
    assert depth[0].item() == pytest.approx(4.0)
    assert px[1, 1] < 24.0  # world up appears at smaller v
    assert px[2, 0] > 32.0  # camera right is world +x
    torch.testing.assert_close(cam.center, pts([0, 0, 4])[0])
    # fx and principal point override
    cam = Camera.from_nerf(c2w, 64, 48, fx=50.0, cy=20.0)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (50.0, 50.0, 32.0, 20.0)
    with pytest.raises(ValueError, match="exactly one"):
        Camera.from_nerf(c2w, 64, 48)


def test_lego_cameras_look_at_the_origin():
    meta = json.loads(require(DATA / "lego" / "transforms_train.json").read_text())
    for frame in meta["frames"][:20]:
        cam = Camera.from_nerf(torch.tensor(frame["transform_matrix"]), 800, 800, fov_x=meta["camera_angle_x"])
        px, depth = cam.project(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5]]))
        assert depth[0] > 2.0
        assert (px[0] - 400.0).abs().max() < 40.0  # the object centre is near the image centre
        assert px[1, 1] < px[0, 1]  # world +z (up in Blender) appears higher


def test_look_at():
    eye, target, up = (3.0, -2.0, 1.5), (0.2, 0.1, 0.4), (0.0, 0.0, 1.0)
    cam = Camera.look_at(eye, target, up, math.radians(50), 80, 60)
    px, depth = cam.project(pts(target, [0.2, 0.1, 0.9]))
    torch.testing.assert_close(px[0], torch.tensor([40.0, 30.0], dtype=torch.float64))
    assert depth[0].item() == pytest.approx(math.dist(eye, target))
    assert px[1, 1] < 30.0 and px[1, 0] == pytest.approx(40.0, abs=1e-6)
    forward = torch.tensor(target) - torch.tensor(eye)
    right = torch.linalg.cross(forward.double(), torch.tensor(up, dtype=torch.float64))
    px_r, _ = cam.project(pts(target)[:] + 0.1 * right / right.norm())
    assert px_r[0, 0] > 40.0
    torch.testing.assert_close(cam.center, torch.tensor(eye, dtype=torch.float64))
    with pytest.raises(ValueError, match="parallel"):
        Camera.look_at((0, 0, 5), (0, 0, 0), (0, 0, 1), 1.0, 8, 8)
    with pytest.raises(ValueError, match="coincide"):
        Camera.look_at((1, 1, 1), (1, 1, 1), (0, 0, 1), 1.0, 8, 8)


def test_derived_matrices_consistent():
    rot = random_rotation(1)
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3], view[:3, 3] = rot, torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    cam = Camera(viewmat=view, fx=100.0, fy=110.0, cx=31.5, cy=20.0, width=64, height=40)
    torch.testing.assert_close(cam.c2w @ cam.viewmat, torch.eye(4, dtype=torch.float64))
    torch.testing.assert_close(cam.R, rot)
    torch.testing.assert_close(cam.center, -rot.T @ cam.t)
    k = torch.tensor([[100.0, 0, 31.5], [0, 110.0, 20.0], [0, 0, 1]], dtype=torch.float64)
    torch.testing.assert_close(cam.K, k)
    _, depth = cam.project(cam.center[None])
    assert abs(depth.item()) < 1e-12


# ------------------------------------------------------------------------------------------ INRIA


def inria_entry(seed: int) -> tuple[dict, torch.Tensor]:
    """An entry as INRIA's camera_to_JSON writes it, plus the world-to-camera matrix it encodes."""
    w2c = np.eye(4)
    w2c[:3, :3] = random_rotation(seed).numpy()
    w2c[:3, 3] = np.random.default_rng(seed).normal(size=3)
    c2w = np.linalg.inv(w2c)  # INRIA: W2C = inv(Rt); pos = W2C[:3, 3]; rot = W2C[:3, :3]
    entry = {
        "id": seed, "img_name": f"img_{seed:03d}", "width": 1000, "height": 700,
        "position": c2w[:3, 3].tolist(), "rotation": [row.tolist() for row in c2w[:3, :3]],
        "fy": 900.5, "fx": 901.25,
    }
    return entry, torch.from_numpy(w2c)


def test_from_inria():
    entry, w2c = inria_entry(3)
    cam = Camera.from_inria(entry)
    torch.testing.assert_close(cam.viewmat, w2c)
    assert (cam.cx, cam.cy, cam.width, cam.height, cam.name) == (500.0, 350.0, 1000, 700, "img_003")
    forward_point = torch.tensor(entry["position"]) + 2.0 * torch.tensor(entry["rotation"])[:, 2]
    px, depth = cam.project(forward_point[None].double())
    torch.testing.assert_close(px[0], torch.tensor([500.0, 350.0], dtype=torch.float64))
    assert depth.item() == pytest.approx(2.0)


def test_inria_round_trip_exact(tmp_path):
    entries = [inria_entry(s)[0] for s in range(5)]
    for e in entries:
        assert Camera.from_inria(e).to_inria(e["id"]) == e
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps(entries))
    cams = load_inria_cameras(path)
    save_inria_cameras(cams, tmp_path / "out.json")
    assert json.loads((tmp_path / "out.json").read_text()) == [dict(e, id=i) for i, e in enumerate(entries)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cameras.json", "out.json"]


def test_inria_keeps_an_off_centre_principal_point_in_extra_keys():
    cam = Camera(viewmat=torch.eye(4), fx=10.0, fy=10.0, cx=5.0, cy=4.0, width=8, height=8)
    entry = cam.to_inria(0)
    assert (entry["cx"], entry["cy"]) == (5.0, 4.0)
    back = Camera.from_inria(entry)
    assert (back.cx, back.cy) == (5.0, 4.0) and torch.allclose(back.viewmat.float(), cam.viewmat)
    assert "cx" not in Camera(viewmat=torch.eye(4), fx=10.0, fy=10.0, cx=4.0, cy=4.0, width=8,
                              height=8).to_inria(0)


# ------------------------------------------------------------------------------------------ helpers


def test_orbit_cameras():
    center = (0.5, -0.25, 1.0)
    cams = orbit_cameras(center, 3.0, 8, width=40, height=30, elevation_deg=20.0, fov_x_deg=60.0)
    assert len(cams) == 8 and [c.name for c in cams[:2]] == ["orbit_000", "orbit_001"]
    c = torch.tensor(center, dtype=torch.float64)
    for cam in cams:
        assert (cam.width, cam.height) == (40, 30) and cam.fov_x == pytest.approx(math.radians(60))
        assert float((cam.center - c).norm()) == pytest.approx(3.0)
        assert float(cam.center[2] - c[2]) == pytest.approx(3.0 * math.sin(math.radians(20)))
        px, depth = cam.project(c[None])
        torch.testing.assert_close(px[0], torch.tensor([20.0, 15.0], dtype=torch.float64))
        assert depth.item() == pytest.approx(3.0)
        up_px, _ = cam.project((c + torch.tensor([0, 0, 0.3], dtype=torch.float64))[None])
        assert up_px[0, 1] < 15.0
    centres = torch.stack([cam.center for cam in cams])
    assert torch.cdist(centres, centres).add(torch.eye(8, dtype=torch.float64) * 9).min() > 1.0
    again = orbit_cameras(center, 3.0, 8, width=40, height=30, elevation_deg=20.0, fov_x_deg=60.0)
    assert all(torch.equal(a.viewmat, b.viewmat) for a, b in zip(cams, again))
    torch.testing.assert_close(cams[0].center, c + 3.0 * torch.tensor(
        [math.cos(math.radians(20)), 0.0, math.sin(math.radians(20))], dtype=torch.float64))


def test_stack():
    cams = orbit_cameras((0, 0, 0), 2.0, 3, width=16, height=12)
    views, ks = stack_viewmats(cams), stack_Ks(cams, dtype=torch.float64)
    assert views.shape == (3, 4, 4) and views.dtype == torch.float32
    assert ks.shape == (3, 3, 3) and ks.dtype == torch.float64
    torch.testing.assert_close(views[1], cams[1].viewmat.float())
    torch.testing.assert_close(ks[2], cams[2].K)


def test_scaled():
    cam = Camera.look_at((0, -3, 1), (0, 0, 0), (0, 0, 1), 1.0, 64, 48)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (32, 24)
    assert half.fov_x == pytest.approx(cam.fov_x) and torch.equal(half.viewmat, cam.viewmat)
    points = pts([0.1, 0.2, 0.3], [-0.5, 0.0, 0.4])
    torch.testing.assert_close(half.project(points)[0], cam.project(points)[0] / 2)
    odd = Camera.from_fov(1.0, 5, 3).scaled(0.5)  # round(2.5) == 2, round(1.5) == 2
    assert (odd.width, odd.height) == (2, 2)
    assert odd.cx == pytest.approx(1.0) and odd.cy == pytest.approx(1.0)
    assert half.to_inria(0)["position"] == cam.to_inria(0)["position"]
    with pytest.raises(ValueError):
        cam.scaled(0.0)


# ------------------------------------------------------------------------------------------ validation


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(fx=0.0), "fx"),
        (dict(fy=-1.0), "fy"),
        (dict(fx=float("inf")), "fx"),
        (dict(cx=float("nan")), "cx"),
        (dict(width=0), "width"),
        (dict(height=2.5), "height"),
        (dict(viewmat=torch.eye(3)), r"\[4, 4\]"),
        (dict(viewmat=torch.eye(4, dtype=torch.int64)), "float"),
        (dict(viewmat=torch.diag(torch.tensor([1.0, 1.0, 1.001, 1.0]))), "orthonormal"),
        (dict(viewmat=torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0]))), "reflection"),
        (dict(viewmat=torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]])), "last row"),
        (dict(viewmat=torch.full((4, 4), float("nan"))), "finite"),
    ],
)
def test_validation(change, match):
    kwargs = dict(viewmat=torch.eye(4), fx=10.0, fy=10.0, cx=4.0, cy=4.0, width=8, height=8)
    kwargs.update(change)
    with pytest.raises(ValueError, match=match):
        Camera(**kwargs)


def test_small_rotation_error_is_tolerated():
    view = torch.eye(4)
    view[0, 1] = 2e-5
    Camera(viewmat=view, fx=1.0, fy=1.0, cx=0.5, cy=0.5, width=1, height=1)
    with pytest.raises(ValueError, match=r"\(0, pi\)"):
        Camera.from_fov(math.pi, 8, 8)
