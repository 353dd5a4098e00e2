"""Tests for gsw.data.nerfstudio: a nerfstudio fixture generated from lego's cameras, with an applied
transform/scale in transforms.json and a training run's dataparser_transforms.json."""

from __future__ import annotations

import json
import math

import pytest
import torch
from helpers import SHARED_DATA, require

from gsw.camera import Camera
from gsw.data import DatasetError, detect_format, load_dataset, load_instant_ngp, load_nerfstudio, write_image
from gsw.data.nerfstudio import normalise_cameras, read_dataparser_transforms

LEGO = SHARED_DATA / "lego"
SIZE = 40


def rigid(angle: float, axis: int, translation) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [k for k in range(3) if k != axis]
    m = torch.eye(4, dtype=torch.float64)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    m[:3, 3] = torch.tensor(translation, dtype=torch.float64)
    return m


APPLIED = rigid(0.7, 0, [0.5, -1.0, 2.0])  # ns-process-data's applied_transform (already in the poses)
ORIENT = rigid(-1.1, 2, [0.3, 0.2, -0.4])  # the dataparser's orientation/centring
POSE_SCALE, APPLIED_SCALE = 0.3, 2.0


def write_dataset(root, n: int = 6, camera_model: str = "OPENCV") -> list[torch.Tensor]:
    """transforms.json + images; returns the OpenGL camera-to-world poses as stored."""
    meta = json.loads(require(LEGO / "transforms_train.json", "shared data").read_text())
    focal = 800 / (2 * math.tan(meta["camera_angle_x"] / 2)) * SIZE / 800
    (root / "images").mkdir(parents=True)
    frames, poses = [], []
    for k, f in enumerate(meta["frames"][:n]):
        pose = APPLIED @ torch.tensor(f["transform_matrix"], dtype=torch.float64)
        write_image(root / "images" / f"frame_{k:05d}.png", torch.full((3, SIZE, SIZE), k / n))
        frames.append({"file_path": f"images/frame_{k:05d}.png", "transform_matrix": pose.tolist(),
                       "colmap_im_id": k + 1})
        poses.append(pose)
    (root / "transforms.json").write_text(json.dumps({
        "w": SIZE, "h": SIZE, "fl_x": focal, "fl_y": focal, "cx": SIZE / 2, "cy": SIZE / 2, "k1": 0.0, "k2": 0.0,
        "p1": 0.0, "p2": 0.0, "camera_model": camera_model, "frames": frames,
        "applied_transform": APPLIED[:3].tolist(), "applied_scale": APPLIED_SCALE}))
    return poses


def write_dataparser(path) -> None:
    path.write_text(json.dumps({"transform": (ORIENT @ APPLIED)[:3].tolist(), "scale": POSE_SCALE * APPLIED_SCALE}))


def test_cameras_in_the_normalised_frame(tmp_path):
    poses = write_dataset(tmp_path / "data")
    write_dataparser(tmp_path / "dataparser_transforms.json")
    assert detect_format(tmp_path / "data") == "nerfstudio"
    ds = load_nerfstudio(tmp_path / "data", dataparser_transforms=tmp_path / "dataparser_transforms.json")
    assert ds.format == "nerfstudio" and ds.meta["frame"] == "normalised" and len(ds) == 6
    assert ds.meta["pose_scale"] == pytest.approx(POSE_SCALE)
    for cam, pose in zip(ds.cameras, poses):
        # nerfstudio's dataparser: poses = orient @ poses; poses[:, :3, 3] *= scale
        expected = ORIENT @ pose
        expected[:3, 3] *= POSE_SCALE
        ref = Camera.from_nerf(expected, SIZE, SIZE, fx=cam.fx)
        assert (cam.viewmat.double() - ref.viewmat.double()).abs().max() <= 1e-6
    # a point of the dataset frame and its image in the model frame project to the same pixel
    raw = load_instant_ngp(tmp_path / "data")
    x = torch.randn(20, 3, dtype=torch.float64) * 0.5
    x_model = POSE_SCALE * (x @ ORIENT[:3, :3].T + ORIENT[:3, 3])
    for a, b in zip(raw.cameras, ds.cameras):
        pa, da = a.project(x)
        pb, db = b.project(x_model)
        torch.testing.assert_close(pb, pa)
        torch.testing.assert_close(db, POSE_SCALE * da)


def test_dataparser_file_found_beside_the_data_and_plain_frame(tmp_path):
    write_dataset(tmp_path)
    plain = load_dataset(tmp_path, "all")
    assert plain.format == "nerfstudio" and plain.meta["frame"] == "dataset"
    reference = load_instant_ngp(tmp_path)
    assert all(torch.equal(a.viewmat, b.viewmat) for a, b in zip(plain.cameras, reference.cameras))
    write_dataparser(tmp_path / "dataparser_transforms.json")
    found = load_dataset(tmp_path, "test")
    assert found.meta["frame"] == "normalised" and len(found) == 1
    transform, scale = read_dataparser_transforms(tmp_path / "dataparser_transforms.json")
    assert scale == pytest.approx(POSE_SCALE * APPLIED_SCALE)
    moved = normalise_cameras(reference.cameras, transform, scale)
    assert not torch.allclose(moved[0].viewmat, found.cameras[0].viewmat)  # the applied transform matters


def test_rejects_unsupported_cameras_and_bad_transforms(tmp_path):
    write_dataset(tmp_path / "fish", n=2, camera_model="OPENCV_FISHEYE")
    with pytest.raises(DatasetError, match="OPENCV_FISHEYE is not supported"):
        load_nerfstudio(tmp_path / "fish")
    write_dataset(tmp_path / "ok", n=2)
    (tmp_path / "bad.json").write_text(json.dumps({"transform": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]],
                                                   "scale": 1.0}))
    with pytest.raises(DatasetError, match="not orthonormal"):
        load_nerfstudio(tmp_path / "ok", dataparser_transforms=tmp_path / "bad.json")
    (tmp_path / "bad.json").write_text(json.dumps({"transform": ORIENT[:3].tolist(), "scale": -1}))
    with pytest.raises(DatasetError, match="'scale' must be a positive number"):
        load_nerfstudio(tmp_path / "ok", dataparser_transforms=tmp_path / "bad.json")
    meta = json.loads((tmp_path / "ok" / "transforms.json").read_text())
    del meta["camera_model"]
    (tmp_path / "ok" / "transforms.json").write_text(json.dumps(meta))
    assert detect_format(tmp_path / "ok") == "instant_ngp"
