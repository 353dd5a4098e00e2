"""The update-space gradient mask: masked elements move less, and the mask survives Adam."""

import torch

from gsw.mark.mask import UpdateMask, exp_mask, stega_mask


def test_mask_shapes_and_ordering() -> None:
    p = torch.tensor([0.0, 0.5, -1.0, 1.5, -2.5])
    m = exp_mask(p)
    assert m.shape == p.shape and m.max() == 1.0
    order = torch.argsort(p.abs())
    assert torch.all(m[order][1:] <= m[order][:-1])  # larger magnitude -> smaller mask
    s = stega_mask(p)
    assert s.max() == 1.0 and torch.all(s[order][1:] <= s[order][:-1])


def _moves(kind: str) -> torch.Tensor:
    init = torch.tensor([0.1, 0.8, 1.2, 1.6])
    p = init.clone().requires_grad_()
    opt = torch.optim.Adam([p], lr=0.05, eps=1e-15)
    mask = UpdateMask([p], kind=kind)
    for _ in range(20):
        opt.zero_grad()
        (p * torch.tensor([1.0, -1.0, 1.0, -1.0])).sum().backward()  # same |gradient| everywhere
        mask.step(opt)
    return (p.detach() - init).abs()


def test_masked_elements_move_less_with_adam() -> None:
    plain = _moves("none")
    masked = _moves("exp")
    # Adam alone moves every element by the same amount (gradients of equal magnitude) ...
    assert torch.allclose(plain, plain[0].expand(4), rtol=1e-5)
    # ... the mask makes larger-magnitude elements move strictly less, in the mask's ratio.
    assert torch.all(masked[1:] < masked[:-1])
    expected = exp_mask(torch.tensor([0.1, 0.8, 1.2, 1.6])) * plain
    assert torch.allclose(masked, expected, rtol=1e-3, atol=1e-6)


def test_gradient_scaling_alone_would_cancel_under_adam() -> None:
    # The official recipe (mask multiplied into .grad) is undone by Adam's normalisation.
    init = torch.tensor([0.1, 1.6])
    p = init.clone().requires_grad_()
    opt = torch.optim.Adam([p], lr=0.05, eps=1e-15)
    m = exp_mask(init)
    for _ in range(5):
        opt.zero_grad()
        p.sum().backward()
        p.grad *= m
        opt.step()
    moved = (p.detach() - init).abs()
    assert torch.allclose(moved[0], moved[1], rtol=1e-3)
