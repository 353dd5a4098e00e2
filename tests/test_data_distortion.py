"""OpenCV radial-tangential distortion: point inverse, image undistortion, loader handling."""

from __future__ import annotations

import json
import math

import pytest
import torch

from gsw.data.distortion import (
    Distortion,
    distort_normalized,
    distort_pixels,
    undistort_image,
    undistort_normalized,
    undistort_pixels,
)
from gsw.data.images import write_image
from gsw.data.loaders import DatasetError, load_instant_ngp

D = Distortion(k1=-0.12, k2=0.03, p1=0.004, p2=-0.003)
W, H = 96, 72
FX, FY, CX, CY = 80.0, 82.0, 49.0, 35.0


def _pattern(uv: torch.Tensor) -> torch.Tensor:
    """A smooth known RGB pattern of ideal (pinhole) pixel coordinates: [..., 2] -> [3, ...]."""
    u, v = uv[..., 0], uv[..., 1]
    return torch.stack([0.5 + 0.4 * torch.sin(u / 7.0), 0.5 + 0.4 * torch.cos(v / 6.0),
                        0.5 + 0.4 * torch.sin((u + v) / 11.0)])


def _pixel_centres(h: int, w: int) -> torch.Tensor:
    jj, ii = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    return torch.stack([ii + 0.5, jj + 0.5], dim=-1)


def _distorted_capture() -> torch.Tensor:
    """What a camera with distortion D records of the pattern: pixel (ud, vd) sees the ideal ray
    undistort(ud, vd)."""
    ideal = undistort_pixels(_pixel_centres(H, W), FX, FY, CX, CY, D)
    return _pattern(ideal).float()


def test_undistort_points_inverts_distort():
    xy = torch.rand(500, 2, dtype=torch.float64) * 1.2 - 0.6
    back = undistort_normalized(distort_normalized(xy, D), D)
    assert torch.allclose(back, xy, atol=1e-10)
    uv = torch.rand(100, 2, dtype=torch.float64) * torch.tensor([W, H], dtype=torch.float64)
    assert torch.allclose(distort_pixels(undistort_pixels(uv, FX, FY, CX, CY, D), FX, FY, CX, CY, D), uv, atol=1e-8)
    assert Distortion().is_identity and not D.is_identity


def test_undistort_image_recovers_pattern():
    captured = _distorted_capture()
    fixed = undistort_image(captured, FX, FY, CX, CY, D)
    truth = _pattern(_pixel_centres(H, W)).float()
    inner = (slice(None), slice(8, H - 8), slice(8, W - 8))
    err = (fixed - truth)[inner].abs()
    assert float(err.max()) < 0.01, float(err.max())
    # the distorted capture itself is clearly different (the test has teeth)
    assert float((captured - truth)[inner].abs().max()) > 0.1


def _write_capture(tmp_path, distortion: Distortion, image: torch.Tensor) -> None:
    (tmp_path / "images").mkdir(exist_ok=True)
    write_image(tmp_path / "images" / "f.png", image)
    meta = {"fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "w": W, "h": H, "k1": distortion.k1, "k2": distortion.k2,
            "p1": distortion.p1, "p2": distortion.p2,
            "frames": [{"file_path": "images/f.png", "transform_matrix": torch.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))


def test_instant_ngp_undistorts(tmp_path):
    _write_capture(tmp_path, D, _distorted_capture())
    ds = load_instant_ngp(tmp_path)
    truth = _pattern(_pixel_centres(H, W)).float()
    err = (ds.images[0] - truth)[:, 8:-8, 8:-8].abs()
    assert float(err.max()) < 0.012  # 8-bit PNG quantisation + bilinear resampling
    with pytest.raises(DatasetError, match="distortion.*undistort=False"):
        load_instant_ngp(tmp_path, undistort=False)


def test_instant_ngp_distorted_marker_projects(tmp_path):
    """A world point's pinhole projection through the loaded camera lands on its (undistorted) blob."""
    # camera at the origin (OpenGL identity: looking down -z); the point is in front of it
    p = torch.tensor([[0.3, -0.2, -2.0]], dtype=torch.float64)
    u_true = CX + FX * 0.3 / 2.0
    v_true = CY - FY * (-0.2) / 2.0

    def blob(uv):
        r2 = (uv[..., 0] - u_true) ** 2 + (uv[..., 1] - v_true) ** 2
        return torch.exp(-r2 / (2 * 2.0**2)).expand(3, *uv.shape[:-1])

    ideal = undistort_pixels(_pixel_centres(H, W), FX, FY, CX, CY, D)
    _write_capture(tmp_path, D, blob(ideal).float())
    ds = load_instant_ngp(tmp_path)
    uv, depth = ds.cameras[0].project(p)
    assert uv[0].tolist() == pytest.approx([u_true, v_true], abs=1e-9) and float(depth) == pytest.approx(2.0)
    img = ds.images[0, 0]
    flat = int(img.argmax())
    assert abs(flat % W + 0.5 - u_true) <= 1.0 and abs(flat // W + 0.5 - v_true) <= 1.0
    # centroid of the blob: sub-pixel agreement
    centres = _pixel_centres(H, W).float()
    wts = img.clamp_min(0.2) - 0.2
    centroid = (centres * wts[..., None]).sum((0, 1)) / wts.sum()
    assert centroid.tolist() == pytest.approx([u_true, v_true], abs=0.15)


def test_fisheye_rejected(tmp_path):
    _write_capture(tmp_path, Distortion(), torch.zeros(3, H, W))
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta["is_fisheye"] = True
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="fisheye"):
        load_instant_ngp(tmp_path)


def test_zero_distortion_is_identity_resample():
    img = torch.rand(3, 10, 12)
    out = undistort_image(img, 10.0, 10.0, 6.0, 5.0, Distortion())
    assert torch.allclose(out, img, atol=1e-5)
    assert math.isclose(float(undistort_image(img[None], 10.0, 10.0, 6.0, 5.0, Distortion())[0].sum()),
                        float(img.sum()), rel_tol=1e-5)
