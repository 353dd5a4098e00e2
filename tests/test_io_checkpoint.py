"""Tests for gsw.io.checkpoint (gsplat .pt and nerfstudio splatfacto .ckpt checkpoints)."""

from __future__ import annotations

import pytest
import torch
from helpers import random_model

from gsw.io import CheckpointError, load_checkpoint, load_gaussians


def gsplat_splats(g) -> dict:
    return {"means": g.means, "quats": g.quats, "scales": g.log_scales, "opacities": g.opacity_logits,
            "sh0": g.sh[:, :1], "shN": g.sh[:, 1:]}


def assert_same(a, b) -> None:
    for name, t in a.parameters().items():
        assert torch.equal(t, b.parameters()[name]), name


@pytest.mark.parametrize("degree", [0, 3])
def test_gsplat_checkpoint(tmp_path, degree):
    g = random_model(50, degree=degree)
    torch.save({"step": 29999, "splats": gsplat_splats(g)}, tmp_path / "ckpt_29999_rank0.pt")
    assert_same(load_gaussians(tmp_path / "ckpt_29999_rank0.pt"), g)
    # float64 / [N, 1] opacities are accepted and cast
    splats = {k: v.double() for k, v in gsplat_splats(g).items()}
    splats["opacities"] = splats["opacities"][:, None]
    torch.save({"splats": splats}, tmp_path / "b.pt")
    h = load_checkpoint(tmp_path / "b.pt")
    assert h.dtype == torch.float32
    assert_same(h, g)


@pytest.mark.parametrize("prefix", ["_model.gauss_params.", "_model."])
def test_splatfacto_checkpoint(tmp_path, prefix):
    g = random_model(40, degree=3)
    state = {"means": g.means, "quats": g.quats, "scales": g.log_scales, "opacities": g.opacity_logits[:, None],
             "features_dc": g.sh[:, 0], "features_rest": g.sh[:, 1:]}
    data = {"step": 100, "pipeline": {prefix + k: v for k, v in state.items()}, "optimizers": {}, "scalers": {}}
    torch.save(data, tmp_path / "step-000000100.ckpt")
    assert_same(load_gaussians(tmp_path / "step-000000100.ckpt"), g)


class NotAllowed:
    """Unpickling this needs code from the test module: refused by weights_only loading."""


def test_rejects_bad_checkpoints(tmp_path):
    g = random_model(10)
    splats = gsplat_splats(g)
    cases = {
        "appearance.pt": ({"splats": {**{k: v for k, v in splats.items() if k not in ("sh0", "shN")},
                                      "features": torch.zeros(10, 32), "colors": torch.zeros(10, 3)}},
                          "appearance-model"),
        "unknown.pt": ({"model": {}}, "unknown checkpoint layout"),
        "list.pt": ([1, 2], "expected a dict"),
        "nan.pt": ({"splats": {**splats, "means": torch.full((10, 3), float("nan"))}}, "non-finite"),
        "shape.pt": ({"splats": {**splats, "quats": torch.zeros(10, 3)}}, "quats"),
        "ints.pt": ({"splats": {**splats, "means": torch.zeros(10, 3, dtype=torch.int64)}}, "floating-point"),
        "nerf.ckpt": ({"pipeline": {"_model.field.weight": torch.zeros(3)}}, "holds no Gaussians"),
        "code.pt": ({"splats": NotAllowed()}, "not a readable torch checkpoint"),
    }
    for name, (content, match) in cases.items():
        torch.save(content, tmp_path / name)
        with pytest.raises(CheckpointError, match=match):
            load_checkpoint(tmp_path / name)
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable torch checkpoint"):
        load_checkpoint(tmp_path / "junk.pt")
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "missing.pt")
