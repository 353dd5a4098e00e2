"""The torch.library custom ops of the rasterizer (gsw/render/_ops.py) and torch.compile of a render."""

from __future__ import annotations

import pytest
import torch

from gsw.camera import Camera
from gsw.gaussians import Gaussians
from gsw.metrics.image import ssim
from gsw.render import _ops
from gsw.render.rasterize import contribution, rasterize
from gsw.scenes import random_gaussians

#: opcheck's test_aot_dispatch_dynamic sums every output into one float and cannot add the int32 radii; the
#: compile test below covers AOT dispatch (forward and backward) instead.
OPCHECKS = ("test_schema", "test_autograd_registration", "test_faketensor")


def _scene(n: int = 60, degree: int = 1) -> tuple[Gaussians, Camera]:
    g = random_gaussians(n, sh_degree=degree, seed=21, extent=0.6)
    return g, Camera.look_at((0.3, -3.0, 0.4), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.9, 24, 20)


def _project_args(g: Gaussians, cam: Camera, check_finite: bool = True) -> tuple:
    leaves = [t.detach().clone().requires_grad_() for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]
    return (*leaves, g.sh_degree, cam.viewmat, float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy),
            cam.width, cam.height, check_finite)


def _detach(t):
    return t.detach() if isinstance(t, torch.Tensor) else t


def test_ops_pass_opcheck() -> None:
    g, cam = _scene()
    pargs = _project_args(g, cam)
    torch.library.opcheck(_ops.project, pargs, test_utils=OPCHECKS)
    radii, m2d, conics, depths, colors, opac, flags = _ops.project(*pargs)
    splats = [t.detach().clone().requires_grad_() for t in (m2d, conics, colors, opac, depths)]
    rargs = (*splats, torch.ones(3, requires_grad=True), radii, cam.width, cam.height, flags)
    torch.library.opcheck(_ops.rasterize, rargs, test_utils=OPCHECKS)
    image, alpha, depth, final_T, n_contrib, *bin_tensors = _ops.rasterize(*rargs)
    torch.library.opcheck(_ops.rasterize_backward, (*[t.detach() for t in rargs[:6]], cam.width, cam.height,
                                                    final_T, n_contrib, *bin_tensors, torch.rand_like(image), None,
                                                    torch.rand_like(depth)), test_utils=OPCHECKS)
    # the restored bins are the binning's
    fresh = _ops.bins(m2d, conics, opac, radii, depths, cam.width, cam.height)
    restored = _ops.restore_bins(cam.width, cam.height, *bin_tensors)
    for name in _ops.BIN_FIELDS:
        assert torch.equal(getattr(restored, name), getattr(fresh, name)), name
    assert restored.num_intersections == fresh.num_intersections > 0
    n = g.means.shape[0]
    vs = [torch.rand(n, 2), torch.rand(n, 3), torch.rand(n), torch.rand(n, 3), torch.rand(n)]
    torch.library.opcheck(_ops.project_backward, (*[_detach(t) for t in pargs[:13]], radii, *vs),
                          test_utils=OPCHECKS)
    weights = torch.rand(2, cam.height, cam.width)
    cargs = (m2d.detach(), conics.detach(), opac.detach(), depths.detach(), radii, weights, cam.width, cam.height)
    torch.library.opcheck(_ops.contribution, cargs, test_utils=OPCHECKS)
    assert torch.equal(_ops.contribution(*cargs)[0], contribution(g, cam, weights).values)


def test_fake_tensors_give_the_output_shapes() -> None:
    from torch._subclasses.fake_tensor import FakeTensorMode
    from torch.fx.experimental.symbolic_shapes import ShapeEnv

    g, cam = _scene(n=7)
    real = [_detach(t) for t in _project_args(g, cam)]
    with FakeTensorMode(shape_env=ShapeEnv()) as mode:
        pargs = [mode.from_tensor(t) if isinstance(t, torch.Tensor) else t for t in real]
        radii, m2d, conics, depths, colors, opac, flags = _ops.project(*pargs)
        image, alpha, depth, final_T, n_contrib, tile_offsets, gauss_ids, entry_offsets, entry_slots = (
            _ops.rasterize(m2d, conics, colors, opac, depths, torch.ones(3), radii, cam.width, cam.height, flags))
    assert [tuple(t.shape) for t in (radii, m2d, conics, depths, colors, opac, flags)] == [
        (7,), (7, 2), (7, 3), (7,), (7, 3), (7,), (1,)]
    assert radii.dtype == torch.int32 and n_contrib.dtype == torch.int32
    assert [tuple(t.shape) for t in (image, alpha, depth, final_T)] == [(3, 20, 24), (1, 20, 24), (1, 20, 24),
                                                                         (20, 24)]
    assert tuple(tile_offsets.shape) == (2 * 2 + 1,) and tuple(entry_offsets.shape) == (8,)
    # the number of tile intersections is an unbacked dynamic size, shared by gauss_ids and entry_slots
    assert isinstance(gauss_ids.shape[0], torch.SymInt) and gauss_ids.shape == entry_slots.shape


def test_torch_compile_fullgraph_render_and_loss_matches_eager() -> None:
    g, cam = _scene(n=120, degree=2)
    gt = torch.rand(3, cam.height, cam.width, generator=torch.Generator().manual_seed(0))

    def loss_fn(means, log_scales, quats, logits, sh):
        out = rasterize(Gaussians(means, log_scales, quats, logits, sh), cam, background=torch.ones(3))
        return 0.8 * (out.image - gt).abs().mean() + 0.2 * (1.0 - ssim(out.image, gt)) + 0.1 * out.depth.mean()

    leaves = [t.detach().clone().requires_grad_() for t in (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh)]
    eager = loss_fn(*leaves)
    eager_grads = torch.autograd.grad(eager, leaves)
    torch._dynamo.reset()
    # aot_eager: Dynamo's full-graph capture, the fake-tensor shapes and AOT autograd of the ops (inductor's C++
    # code generation would only add minutes of compile time to the suite).
    compiled = torch.compile(loss_fn, fullgraph=True, backend="aot_eager")
    value = compiled(*leaves)
    grads = torch.autograd.grad(value, leaves)
    torch.testing.assert_close(value, eager, rtol=1e-6, atol=1e-7)
    for a, b in zip(grads, eager_grads):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
    assert eager_grads[0].abs().sum() > 0


def test_nonfinite_inputs_are_reported_through_the_op() -> None:
    g, cam = _scene(n=10)
    bad = g.clone()
    bad.means[4, 1] = float("inf")
    with pytest.raises(ValueError, match="means: 1 of 10"):
        rasterize(bad, cam)
    pargs = _project_args(bad, cam)
    radii, m2d, conics, depths, colors, opac, flags = _ops.project(*pargs)
    with pytest.raises(_ops.NonFiniteInputError, match="means") as info:
        _ops.rasterize(m2d, conics, colors, opac, depths, torch.ones(3), radii, cam.width, cam.height, flags)
    assert info.value.flags == 1


def test_eager_calls_skip_the_dispatch_with_the_same_results(monkeypatch) -> None:
    """A render on plain tensors runs the ops' implementations in a plain autograd function (no custom-op dispatch):
    image, depth and every gradient equal the dispatched op's bit for bit; traced calls keep the op."""
    g, cam = _scene(n=80, degree=2)

    def render_and_grads():
        leaves = [t.detach().clone().requires_grad_() for t in (g.means, g.log_scales, g.quats, g.opacity_logits,
                                                                g.sh)]
        out = rasterize(Gaussians(*leaves), cam, background=torch.tensor([0.2, 0.3, 0.4]))
        (out.image.square().sum() + out.depth.mean() + out.alpha.sum()).backward()
        return [out.image, out.depth, *[t.grad for t in leaves]]

    ops_called = []
    for name in ("project", "rasterize"):
        op = getattr(_ops, name)
        monkeypatch.setitem(_ops._EAGER, op, (lambda f, n: lambda *a: ops_called.append(n) or f(*a))(
            _ops._EAGER[op], name))
    eager = render_and_grads()
    assert ops_called == ["project", "rasterize"]
    monkeypatch.setattr(_ops, "_traced", lambda args: True)  # every call through the custom ops
    dispatched = render_and_grads()
    assert ops_called == ["project", "rasterize"]  # the eager table was not used again
    for a, b in zip(eager, dispatched):
        assert torch.equal(a, b)


def test_traced_calls_go_through_the_op() -> None:
    from torch._subclasses.fake_tensor import FakeTensorMode

    g, cam = _scene(n=7)
    real = [_detach(t) for t in _project_args(g, cam)]
    assert not _ops._traced(tuple(real))
    with FakeTensorMode() as mode:
        fake = [mode.from_tensor(t) if isinstance(t, torch.Tensor) else t for t in real]
        assert _ops._traced(tuple(fake))
        radii = _ops.call(_ops.project, *fake)[0]
    assert radii.shape == (7,) and type(radii) is not torch.Tensor  # a fake tensor from the op's fake kernel


def test_tensor_subclasses_are_traced_and_parameters_are_not() -> None:
    class Sub(torch.Tensor):
        pass

    g, cam = _scene(n=7)
    real = tuple(_detach(t) for t in _project_args(g, cam))
    assert not _ops._traced(real)
    assert not _ops._traced((torch.nn.Parameter(real[0]), *real[1:]))
    assert _ops._traced((real[0].as_subclass(Sub), *real[1:]))
    assert _ops._traced((*real[:-1], real[0].as_subclass(Sub)))  # wherever it is


def test_calls_inside_a_functorch_transform_are_traced() -> None:
    g, cam = _scene(n=7)
    real = tuple(_detach(t) for t in _project_args(g, cam))
    seen = []

    def probe(x):
        seen.append(_ops._traced((x, *real[1:])))
        return x

    torch.func.vmap(probe)(real[0][None])
    assert seen == [True]


def test_restored_bins_reject_tensors_of_another_binning() -> None:
    g, cam = _scene(n=30)
    pargs = _project_args(g, cam)
    radii, m2d, conics, depths, _, opac, _ = _ops.project(*pargs)
    b = _ops.bins(m2d, conics, opac, radii, depths, cam.width, cam.height)
    t = [b.tile_offsets, b.gauss_ids, b.entry_offsets, b.entry_slots]
    with pytest.raises(RuntimeError, match="tile_offsets"):  # another image size
        _ops.restore_bins(cam.width + 16, cam.height, *t)
    with pytest.raises(RuntimeError, match="entry_slots"):  # lengths disagree
        _ops.restore_bins(cam.width, cam.height, t[0], t[1], t[2], t[3][:-1])
    with pytest.raises(RuntimeError, match="gauss_ids"):
        _ops.restore_bins(cam.width, cam.height, t[0], t[1].long(), t[2], t[3])
    with pytest.raises(RuntimeError, match="width/height"):
        _ops.restore_bins(0, cam.height, *t)


@pytest.mark.parametrize("degree", [0, 3])
def test_projection_keeps_none_of_its_outputs_but_the_radii(degree) -> None:
    # The projection's backward recomputes the conics, colours and opacities: its node holds the inputs and the
    # radii only, so those outputs are freed once the blending's backward (which needs them) has run, before the
    # projection's gradients are allocated.
    g, cam = _scene(degree=degree)
    leaves = [t.detach().clone().requires_grad_() for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]
    out = rasterize(Gaussians(*(leaves[k] for k in (0, 2, 1, 3, 4))), cam)
    proj = out.projection
    node = proj.conics.grad_fn
    saved = node.saved_tensors
    kept = {t.untyped_storage().data_ptr() for t in saved}
    for name in ("means2d", "conics", "colors", "opacities", "depths"):
        assert getattr(proj, name).untyped_storage().data_ptr() not in kept, name
    assert proj.radii.untyped_storage().data_ptr() in kept
    assert len(saved) == 7
    # and the recomputed gradients are the reference's (the kernels' parity tests cover every path)
    (out.image.square().sum() + out.alpha.sum()).backward()
    assert all(t.grad is not None and torch.isfinite(t.grad).all() for t in leaves)
