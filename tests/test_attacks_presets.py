"""Tests for :mod:`gsw.attacks.presets` (the named attack tables)."""

from __future__ import annotations

import pytest
import torch

from gsw import attacks as A
from gsw.attacks.presets import PAPER_IMAGE_ATTACKS

H, W = 64, 48


def _image(batch: int | None = None) -> torch.Tensor:
    x = torch.rand(batch or 1, 3, H, W, generator=torch.Generator().manual_seed(0))
    return x[0] if batch is None else x


PAPER_CROP_HW = A.crop_size(H, W, PAPER_IMAGE_ATTACKS["crop"]["keep_area"])
EXPECTED_HW = {
    "noise": (H, W),
    "rotation": (H, W),
    "scaling": A.scaled_size(H, W, PAPER_IMAGE_ATTACKS["scaling"]["factor"]),
    "blur": (H, W),
    "crop": PAPER_CROP_HW,
    "jpeg": (H, W),
    "combined": PAPER_CROP_HW,
    "brightness": (H, W),
    "contrast": (H, W),
}


@pytest.mark.parametrize("name", sorted(A.IMAGE_ATTACKS))
@pytest.mark.parametrize("batched", [False, True])
def test_image_attack_shape_and_range(name, batched):
    img = _image(batch=2 if batched else None)
    out = A.IMAGE_ATTACKS[name](img)
    lead = (2, 3) if batched else (3,)
    assert out.shape == lead + EXPECTED_HW[name]
    assert out.dtype == img.dtype
    assert out.min() >= 0 and out.max() <= 1
    assert torch.equal(img, _image(batch=2 if batched else None))  # input untouched


@pytest.mark.parametrize("name", sorted(A.OFFICIAL_ATTACKS))
def test_official_attack_shape_and_range(name):
    out = A.OFFICIAL_ATTACKS[name](_image())
    assert out.shape == (3,) + ((H, W) if name != "crop" else A.crop_size(H, W, 0.5))
    assert out.min() >= 0 and out.max() <= 1


@pytest.mark.parametrize("name", sorted(PAPER_IMAGE_ATTACKS))
def test_paper_table_is_what_the_named_attacks_apply(name):
    img = _image(batch=2)
    assert torch.equal(A.IMAGE_ATTACKS[name](img), A.IMAGE_ATTACKS[name](img, **PAPER_IMAGE_ATTACKS[name]))


def test_sweeps():
    img = _image()
    for name in A.SWEEPS:
        values = A.sweep(name)
        assert len(values) >= 4
        key = A.sweep_parameter(name)
        out = A.IMAGE_ATTACKS[name](img, **{key: values[2]})
        assert out.min() >= 0 and out.max() <= 1
    with pytest.raises(KeyError):
        A.sweep("nope")


def test_sweeps_pass_through_the_paper_strengths():
    swept = [name for name in PAPER_IMAGE_ATTACKS if name in A.SWEEPS]
    assert swept
    for name in swept:
        assert PAPER_IMAGE_ATTACKS[name][A.sweep_parameter(name)] in A.sweep(name), name


def test_bind_model_attacks():
    cameras = [object(), object()]
    bound = A.bind_model_attacks(["remove", "finetune"], cameras, background=(1.0, 1.0, 1.0))
    assert bound["remove"] is A.remove_random  # needs no views: the attack itself
    assert bound["finetune"].func is A.finetune
    assert bound["finetune"].keywords == {"cameras": cameras, "background": (1.0, 1.0, 1.0)}
    with pytest.raises(KeyError, match="unknown model attacks"):
        A.bind_model_attacks(["finetuning"], cameras)
