"""Training photos (gsw.decoder.pretrain.data): loading, host crops, the device image bank."""

import numpy as np
import pytest
import torch
from PIL import Image

from gsw.decoder.pretrain.data import bank_crops, image_bank, load_images, load_split, photo_paths, random_crops


def _write_photos(folder, sizes):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i, (h, w) in enumerate(sizes):
        Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(folder / f"{i:02d}.png")
    (folder / "notes.txt").write_text("not a photo")


def test_load_images_in_name_order_with_limit_and_clear_errors(tmp_path):
    _write_photos(tmp_path / "d" / "train", [(20, 30), (30, 20), (24, 24)])
    imgs = load_images(tmp_path / "d" / "train")
    assert [tuple(i.shape) for i in imgs] == [(3, 20, 30), (3, 30, 20), (3, 24, 24)]
    assert imgs[0].dtype == torch.uint8
    assert len(load_split(tmp_path / "d", "train", limit=2)) == 2
    assert [p.name for p in photo_paths(tmp_path / "d" / "train")] == ["00.png", "01.png", "02.png"]
    with pytest.raises(FileNotFoundError, match="photo folder not found: .*val"):
        load_split(tmp_path / "d", "val")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no images in"):
        load_images(tmp_path / "empty")


def test_image_bank_is_landscape_and_centre_cropped_to_the_common_size():
    a = torch.arange(3 * 20 * 30).reshape(3, 20, 30).to(torch.uint8)
    b = torch.zeros(3, 32, 22, dtype=torch.uint8)  # portrait: transposed to 22 x 32
    bank = image_bank([a, b], "cpu")
    assert bank.shape == (2, 3, 20, 30)
    assert torch.equal(bank[0], a)


def test_crops_have_the_size_range_and_determinism():
    g = torch.Generator().manual_seed(0)
    bank = (torch.rand(3, 3, 40, 50, generator=g) * 255).to(torch.uint8)
    c1 = bank_crops(bank, 5, 16, torch.Generator().manual_seed(1))
    c2 = bank_crops(bank, 5, 16, torch.Generator().manual_seed(1))
    assert c1.shape == (5, 3, 16, 16) and torch.equal(c1, c2)
    assert c1.min() >= 0 and c1.max() <= 1
    # every crop is a (possibly flipped) window of a bank image
    vals = set(bank.flatten().tolist())
    assert set((c1 * 255).round().to(torch.uint8).flatten().tolist()) <= vals
    small = [torch.zeros(3, 8, 8, dtype=torch.uint8)]
    assert random_crops(small, 2, 16, torch.Generator().manual_seed(0), "cpu").shape == (2, 3, 16, 16)  # enlarged
