"""Evaluation helpers (gsw.decoder.pretrain.evaluation): batched attack evaluation."""

import pytest
import torch

from gsw.decoder.pretrain.evaluation import eval_attacks
from gsw.attacks.layers import JPEG, Combined, Crop, GaussianBlur, Identity, Resize, draws_per_batch


def test_eval_attacks_batches_same_size_images_without_changing_the_measurement():
    g = torch.Generator().manual_seed(0)
    sizes = [(32, 48), (32, 48), (48, 32), (32, 48), (48, 32)]
    images = [torch.randint(0, 256, (3, *s), generator=g, dtype=torch.uint8) for s in sizes]
    attacks = {"identity": Identity(), "blur": GaussianBlur(sigma=(0.5, 0.5), fixed=True)}
    k = 16

    def run(n):
        shapes = []

        def embed(x, m):
            shapes.append(tuple(x.shape))
            return x + 0.01  # every pair at the same PSNR

        # a decoder that always reads 1: accuracy is the share of ones in the messages drawn
        r = eval_attacks(embed, lambda ll: torch.ones(ll.shape[0], k), images, attacks, k, msgs_per_image=3,
                         seed=5, images_per_batch=n)
        return r, shapes

    one, shapes1 = run(1)
    two, shapes2 = run(2)
    assert shapes1 == [(3, 3, *s) for s in sizes]  # one by one, in order
    assert shapes2 == [(6, 3, 32, 48), (6, 3, 48, 32), (3, 3, 32, 48)]  # groups of one size
    assert one["n"] == two["n"] == 15
    # the same messages are drawn (assigned to other images): the same accuracy and PSNR
    assert one["bit_acc"] == pytest.approx(two["bit_acc"])
    assert 0.3 < one["bit_acc"]["identity"] < 0.7
    assert one["psnr"] == pytest.approx(two["psnr"], abs=1e-4)
    # per image, in the images' order however they were grouped: an oracle that reads the tall images'
    # messages right and every bit of the wide ones wrong
    for n in (1, 2):
        sent = []

        def embed_oracle(x, m):
            sent.append((m * 2 - 1) * (1.0 if x.shape[-1] == 32 else -1.0))
            return x

        r = eval_attacks(embed_oracle, lambda ll: sent[-1], images, {"identity": Identity()}, k, msgs_per_image=3,
                         seed=5, images_per_batch=n, per_image=True)
        assert r["per_image"]["identity"] == [1.0 if s[1] == 32 else 0.0 for s in sizes]
    with pytest.raises(ValueError, match="images_per_batch must be >= 1"):
        eval_attacks(lambda x, m: x, lambda ll: ll, images, attacks, k, images_per_batch=0)


def test_every_pair_draws_its_own_strength():
    assert draws_per_batch(Resize()) and draws_per_batch(Combined([Crop(), JPEG((90, 60))]))
    assert not draws_per_batch(Resize((0.5, 0.5), fixed=True)) and not draws_per_batch(Identity())
    g = torch.Generator().manual_seed(0)
    images = [torch.randint(0, 256, (3, 64, 64), generator=g, dtype=torch.uint8) for _ in range(4)]
    seen = []

    def decode(ll):
        seen.append(tuple(ll.shape))
        return torch.ones(ll.shape[0], 8)

    r = eval_attacks(lambda x, m: x, decode, images, {"resize": Resize(scale=(1.0, 0.5))}, 8, msgs_per_image=3,
                     seed=1, images_per_batch=4)
    assert r["n"] == 12 and len(seen) == 12 and all(s[0] == 1 for s in seen)  # one decode per pair
    assert len(set(seen)) > 6  # scales drawn per pair, not one per batch of 12


def test_bootstrap_interval_of_the_mean():
    from gsw.stats import bootstrap_ci95

    assert bootstrap_ci95([0.9] * 20) == pytest.approx([0.9, 0.9])
    vals = torch.rand(200, generator=torch.Generator().manual_seed(0)).tolist()
    lo, hi = bootstrap_ci95(vals)
    mean = sum(vals) / len(vals)
    assert lo < mean < hi and hi - lo < 0.1  # ~ +-1.96 * 0.29 / sqrt(200) = +-0.04
    assert bootstrap_ci95(vals) == [lo, hi]  # seeded
