"""gsw.losses: the 3D-GSW fine-tuning objective."""

from __future__ import annotations

import pytest
import torch

from gsw.mark.loss import LossWeights, WatermarkLoss, message_loss, subband_l1


def _image(seed: int = 0, size: int = 32) -> torch.Tensor:
    return torch.rand(3, size, size, generator=torch.Generator().manual_seed(seed))


def test_subband_loss_zero_for_identical_images() -> None:
    x = _image()
    assert float(subband_l1(x, x.clone())) == 0.0


def test_subband_loss_ignores_ll() -> None:
    # a constant offset lives in LL only (the high-pass filters sum to zero): L1 sees it, the subband loss not
    x = _image()
    assert float(subband_l1(x + 0.1, x)) < 1e-5
    y = x.clone()
    y[:, :, ::2] += 0.1  # a column stripe pattern: high frequencies
    assert float(subband_l1(y, x)) > 1e-2


def _wrong_to_right_gradient(scale: float) -> float:
    logits = torch.tensor([[2.0, -0.5]], requires_grad=True)  # bit 0 right, bit 1 wrong (message 1, 1)
    message_loss(logits, torch.tensor([1.0, 1.0]), scale).backward()
    g = logits.grad.abs()[0]
    return float(g[1] / g[0])


def test_message_loss_scale_concentrates_on_wrong_bits() -> None:
    # x10 logits: the right bit's gradient vanishes, the wrong one's does not
    assert _wrong_to_right_gradient(10.0) > 100 * _wrong_to_right_gradient(1.0)


def test_message_loss_is_plain_bce_at_scale_one() -> None:
    x = torch.tensor([[0.3, -1.2, 2.0]])
    m = torch.tensor([1.0, 0.0, 0.0])
    ref = torch.nn.functional.binary_cross_entropy_with_logits(x, m[None])
    assert torch.allclose(message_loss(x, m), ref)


class _MeanDecoder(torch.nn.Module):
    def forward(self, ll: torch.Tensor) -> torch.Tensor:
        return ll.mean(dim=(2, 3))[:, :2] - 0.5


def test_watermark_loss_total_is_the_weighted_sum() -> None:
    w = LossWeights(l1=1.0, lpips=0.0, subband=0.3, message=0.2, mse=7.0)
    fn = WatermarkLoss(_MeanDecoder(), w, lpips_net=None, logit_scale=2.0)
    x, y, msg = _image(1), _image(2), torch.tensor([1.0, 0.0])
    total, terms, logits = fn(x, y, msg)
    assert set(terms) == {"l1", "mse", "subband", "message"} and logits.shape == (2,)
    assert abs(terms["mse"] - float((x - y).square().mean())) < 1e-7
    expect = terms["l1"] + 7.0 * terms["mse"] + 0.3 * terms["subband"] + 0.2 * terms["message"]
    assert abs(float(total) - expect) < 1e-5
    assert abs(terms["message"] - float(message_loss(logits[None], msg, 2.0))) < 1e-6


def test_watermark_loss_bad_settings() -> None:
    with pytest.raises(ValueError, match="logit_scale"):
        WatermarkLoss(_MeanDecoder(), LossWeights(lpips=0.0), lpips_net=None, logit_scale=0.0)
    with pytest.raises(ValueError, match="LPIPS is disabled"):
        WatermarkLoss(_MeanDecoder(), LossWeights(), lpips_net=None)


def test_weight_control_holds_the_target_within_its_range() -> None:
    from gsw.mark.loss import WeightControl

    ctl = WeightControl(0.2, target=37.0, adapt=2.0, max_factor=4.0, check_every=2, span=1)
    assert ctl.observe(40.0) == 0.2  # no check yet
    assert ctl.observe(40.0) == pytest.approx(0.4)  # above the target: more message
    weights = [ctl.observe(40.0) for _ in range(10)]
    assert max(weights) == pytest.approx(0.8)  # capped at 4x
    weights = [ctl.observe(30.0) for _ in range(20)]
    assert weights[-1] == pytest.approx(0.05)  # below the target: less, floored at 1/4
    with pytest.raises(ValueError, match="adapt"):
        WeightControl(0.2, 37.0, adapt=1.0)
