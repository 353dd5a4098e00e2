"""The rasterizer kernels as ``torch.library`` custom ops (``gsw::...``), with fake-tensor shapes and autograd.

The autograd wrappers of :mod:`gsw.render.rasterize` call these ops through :func:`call` and nothing else, so
``torch.compile`` traces a render (and its backward) without graph breaks, eager and compiled runs use the same
kernels, and the ops work on any device the extension was built for. Eager calls on plain tensors skip the
custom-op dispatch (:func:`call`: the op's own implementation, setup and backward in a plain autograd function).

Ops:

* ``gsw::project`` -> (radii, means2d, conics, depths, colors, opacities, nonfinite); ``gsw::project_backward``.
* ``gsw::rasterize`` -> (image, alpha, depth, final_T, n_contrib, tile_offsets, gauss_ids, entry_offsets,
  entry_slots): tile binning and blending in one op. The bins are outputs too, for the backward op and for
  :func:`restore_bins`; the number of tile intersections (the length of ``gauss_ids`` / ``entry_slots``) is
  data-dependent: the fake implementation gives it as an unbacked dynamic size. ``gsw::rasterize_backward``.
* ``gsw::contribution`` -> (values, hits, max_weight): binning and the contribution kernel (no gradient).

A projection run with ``check_finite`` flags NaN/Inf inputs in its ``nonfinite`` output; ``gsw::rasterize`` reads
the flags back with the binning's host synchronisation and raises :class:`NonFiniteInputError`.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from gsw._ext import _C

__all__ = ["NonFiniteInputError", "bins", "call", "contribution", "project", "rasterize", "restore_bins"]


class NonFiniteInputError(ValueError):
    """Inputs of a render hold NaN/Inf; ``flags`` has bit k set for ``_C.NONFINITE_FIELDS[k]`` (``names``)."""

    def __init__(self, flags: int) -> None:
        self.flags = int(flags)
        self.names = [name for k, name in enumerate(_C.NONFINITE_FIELDS) if self.flags >> k & 1]
        super().__init__("non-finite Gaussian parameters: " + ", ".join(self.names))


def bins(means2d: Tensor, conics: Tensor, opacities: Tensor, radii: Tensor, depths: Tensor, width: int,
         height: int, nonfinite: Tensor | None = None) -> Any:
    """The tile binning (``_C.TileBins``) of projected Gaussians (not differentiable): each one goes to the tiles
    of its radius rectangle that its opacity-aware ellipse reaches (``csrc/core/tiles.h``)."""
    return _C.bin_gaussians(_c(means2d), _c(conics), _c(opacities), radii.contiguous(), _c(depths), int(width),
                            int(height), nonfinite=nonfinite)


def _c(t: Tensor) -> Tensor:
    # No detach(): the ops run with gradients off (inside autograd functions and backward passes, or as custom-op
    # implementations) and read their inputs' data only.
    return t.contiguous()


# ----------------------------------------------------------------------------------------------- projection

def _project_impl(means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, sh: Tensor,
                  sh_degree: int, viewmat: Tensor, fx: float, fy: float, cx: float, cy: float, width: int,
                  height: int, check_finite: bool) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """EWA projection + SH colour: (radii [N] int32, means2d [N,2], conics [N,3], depths [N], colors [N,3],
    opacities [N], nonfinite [1] int32 flags (zero unless ``check_finite``))."""
    flags = torch.zeros(1, dtype=torch.int32, device=means.device)
    out = _C.project_forward(_c(means), _c(quats), _c(log_scales), _c(opacity_logits), _c(sh), sh_degree=sh_degree,
                             viewmat=viewmat.detach(), fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height,
                             nonfinite=flags if check_finite else None)
    return (*out, flags)


project = torch.library.custom_op("gsw::project", mutates_args=())(_project_impl)


@project.register_fake
def _(means, quats, log_scales, opacity_logits, sh, sh_degree, viewmat, fx, fy, cx, cy, width, height,
      check_finite):
    n = means.shape[0]
    new = means.new_empty
    return (new((n,), dtype=torch.int32), new((n, 2)), new((n, 3)), new((n,)), new((n, 3)), new((n,)),
            new((1,), dtype=torch.int32))


def _project_backward_impl(means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, sh: Tensor,
                           sh_degree: int, viewmat: Tensor, fx: float, fy: float, cx: float, cy: float, width: int,
                           height: int, radii: Tensor, v_means2d: Tensor, v_conics: Tensor, v_depths: Tensor,
                           v_colors: Tensor, v_opacities: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """VJP of ``gsw::project``: (v_means, v_quats, v_log_scales, v_opacity_logits, v_sh). It reads the inputs and
    ``radii`` only: the conics, colours and opacities are recomputed, so a render does not keep them for it."""
    return tuple(_C.project_backward(
        _c(means), _c(quats), _c(log_scales), _c(opacity_logits), _c(sh), sh_degree=sh_degree,
        viewmat=viewmat.detach(), fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height, radii=_c(radii),
        v_means2d=_c(v_means2d), v_conics=_c(v_conics), v_depths=_c(v_depths), v_colors=_c(v_colors),
        v_opacities=_c(v_opacities)))


project_backward = torch.library.custom_op("gsw::project_backward", mutates_args=())(_project_backward_impl)


@project_backward.register_fake
def _(means, quats, log_scales, opacity_logits, sh, *args):
    return tuple(torch.empty_like(t, memory_format=torch.contiguous_format)
                 for t in (means, quats, log_scales, opacity_logits, sh))


def _project_setup(ctx, inputs, output) -> None:
    means, quats, log_scales, opacity_logits, sh, sh_degree, viewmat, fx, fy, cx, cy, width, height, _ = inputs
    radii = output[0]
    ctx.args = dict(sh_degree=sh_degree, fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height)
    # The radii alone of the outputs: the backward recomputes the rest, so after the blending's backward has run
    # the projected conics, colours and opacities are freed before the projection's gradients are allocated.
    ctx.save_for_backward(means, quats, log_scales, opacity_logits, sh, viewmat, radii)
    ctx.mark_non_differentiable(radii, output[6])


def _project_backward(ctx, _v_radii, v_means2d, v_conics, v_depths, v_colors, v_opacities, _v_flags):
    means, quats, log_scales, opacity_logits, sh, viewmat, radii = ctx.saved_tensors
    a = ctx.args
    cotangents = [v_means2d, v_conics, v_depths, v_colors, v_opacities]
    if any(v is None for v in cotangents):  # outputs that got no gradient: zeros of their shapes
        n = means.shape[0]
        shapes = ((n, 2), (n, 3), (n,), (n, 3), (n,))
        cotangents = [means.new_zeros(s) if v is None else v for v, s in zip(cotangents, shapes)]
    grads = call(
        project_backward, means, quats, log_scales, opacity_logits, sh, a["sh_degree"], viewmat, a["fx"], a["fy"],
        a["cx"], a["cy"], a["width"], a["height"], radii, *cotangents)
    return (*grads, None, None, None, None, None, None, None, None, None)


project.register_autograd(_project_backward, setup_context=_project_setup)


# ----------------------------------------------------------------------------------------------- blending

def _raise_if_flagged(b: Any) -> None:
    if b.nonfinite:
        raise NonFiniteInputError(b.nonfinite)


BIN_FIELDS = ("tile_offsets", "gauss_ids", "entry_offsets", "entry_slots")


def restore_bins(width: int, height: int, tile_offsets: Tensor, gauss_ids: Tensor, entry_offsets: Tensor,
                 entry_slots: Tensor) -> Any:
    """A ``_C.TileBins`` over the given bin tensors (outputs of ``gsw::rasterize``), without binning again (no
    copy, no host synchronisation; the binding checks that they form one binning for the image size)."""
    return _C.TileBins(tile_offsets.contiguous(), gauss_ids.contiguous(), entry_offsets.contiguous(),
                       entry_slots.contiguous(), int(width), int(height))


def _rasterize_impl(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, depths: Tensor,
                    background: Tensor, radii: Tensor, width: int, height: int, nonfinite: Tensor | None
                    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Binning + front-to-back blending: (image [3,H,W], alpha [1,H,W], depth [1,H,W], final_T [H,W],
    n_contrib [H,W] int32, then the bins: tile_offsets [tiles+1], gauss_ids [M], entry_offsets [N+1],
    entry_slots [M], all int32, M the data-dependent number of tile intersections). Raises
    :class:`NonFiniteInputError` when ``nonfinite`` (the projection's flags) is set."""
    b = bins(means2d, conics, opacities, radii, depths, width, height, nonfinite)
    _raise_if_flagged(b)
    out = _C.rasterize_forward(_c(means2d), _c(conics), _c(colors), _c(opacities), _c(depths), _c(background),
                               bins=b, width=width, height=height)
    return (*out, *(getattr(b, name) for name in BIN_FIELDS))


rasterize = torch.library.custom_op("gsw::rasterize", mutates_args=())(_rasterize_impl)


@rasterize.register_fake
def _(means2d, conics, colors, opacities, depths, background, radii, width, height, nonfinite):
    new = means2d.new_empty
    m = torch.library.get_ctx().new_dynamic_size()
    tiles = -(-width // _C.constants["TILE_SIZE"]) * -(-height // _C.constants["TILE_SIZE"])
    i32 = {"dtype": torch.int32}
    return (new((3, height, width)), new((1, height, width)), new((1, height, width)), new((height, width)),
            new((height, width), **i32), new((tiles + 1,), **i32), new((m,), **i32),
            new((means2d.shape[0] + 1,), **i32), new((m,), **i32))


def _rasterize_backward_impl(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, depths: Tensor,
                             background: Tensor, width: int, height: int, final_T: Tensor, n_contrib: Tensor,
                             tile_offsets: Tensor, gauss_ids: Tensor, entry_offsets: Tensor, entry_slots: Tensor,
                             v_image: Tensor, v_alpha: Tensor | None, v_depth: Tensor | None
                             ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """VJP of ``gsw::rasterize`` on its bins: (v_means2d, v_conics, v_colors, v_opacities, v_depths)."""
    b = restore_bins(width, height, tile_offsets, gauss_ids, entry_offsets, entry_slots)
    return tuple(_C.rasterize_backward(
        _c(means2d), _c(conics), _c(colors), _c(opacities), _c(depths), _c(background), bins=b, width=width,
        height=height, final_T=_c(final_T), n_contrib=_c(n_contrib), v_image=_c(v_image),
        v_alpha=None if v_alpha is None else _c(v_alpha), v_depth=None if v_depth is None else _c(v_depth)))


rasterize_backward = torch.library.custom_op("gsw::rasterize_backward", mutates_args=())(_rasterize_backward_impl)


@rasterize_backward.register_fake
def _(means2d, conics, colors, opacities, depths, *args):
    return tuple(torch.empty_like(t, memory_format=torch.contiguous_format)
                 for t in (means2d, conics, colors, opacities, depths))


def _rasterize_setup(ctx, inputs, output) -> None:
    means2d, conics, colors, opacities, depths, background, radii, width, height, _ = inputs
    ctx.size = (width, height)
    ctx.save_for_backward(means2d, conics, colors, opacities, depths, background, *output[3:])
    ctx.mark_non_differentiable(*output[3:])
    # Unused outputs (usually alpha and depth) get no zero-filled [1, H, W] cotangents: the kernels treat a
    # missing v_alpha / v_depth as zero.
    ctx.set_materialize_grads(False)


def _rasterize_backward(ctx, v_image, v_alpha, v_depth, *_v_rest):
    means2d, conics, colors, opacities, depths, background, final_T, *saved = ctx.saved_tensors
    width, height = ctx.size
    if v_image is None:
        v_image = means2d.new_zeros((3, height, width))
    grads = call(rasterize_backward, means2d, conics, colors, opacities, depths, background, width, height,
                 final_T, *saved, v_image, v_alpha, v_depth)
    v_background = None
    if ctx.needs_input_grad[5]:
        v_background = (v_image * final_T.unsqueeze(0)).sum(dim=(1, 2))
    return (*grads, v_background, None, None, None, None)


rasterize.register_autograd(_rasterize_backward, setup_context=_rasterize_setup)


# ----------------------------------------------------------------------------------------------- contribution

def _contribution_impl(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, radii: Tensor,
                       weights: Tensor, width: int, height: int) -> tuple[Tensor, Tensor, Tensor]:
    """Binning + per-Gaussian weighted blending weights: (values [N, C], hits [N] int32, max_weight [N])."""
    b = bins(means2d, conics, opacities, radii, depths, width, height)
    return tuple(_C.contribution(_c(means2d), _c(conics), _c(opacities), bins=b, width=width, height=height,
                                 weights=_c(weights)))


contribution = torch.library.custom_op("gsw::contribution", mutates_args=())(_contribution_impl)


@contribution.register_fake
def _(means2d, conics, opacities, depths, radii, weights, width, height):
    n, c = means2d.shape[0], weights.shape[0]
    return (means2d.new_empty((n, c)), means2d.new_empty((n,), dtype=torch.int32), means2d.new_empty((n,)))


# ----------------------------------------------------------------------------------------------- eager calls

def _autograd_function(impl, setup, backward):
    """A plain ``torch.autograd.Function`` around an op's implementation, ``setup_context`` and backward: the very
    functions the custom op registers, without its dispatch."""

    class EagerOp(torch.autograd.Function):
        @staticmethod
        def forward(ctx, *args):
            out = impl(*args)
            setup(ctx, args, out)
            return out

        @staticmethod
        def backward(ctx, *grads):
            return backward(ctx, *grads)

    return EagerOp.apply


_EAGER = {
    project: _autograd_function(_project_impl, _project_setup, _project_backward),
    rasterize: _autograd_function(_rasterize_impl, _rasterize_setup, _rasterize_backward),
    project_backward: _project_backward_impl,  # called inside backward passes: no gradient of their own
    rasterize_backward: _rasterize_backward_impl,
    contribution: _contribution_impl,  # inputs detached: no gradient
}


def _traced(args: tuple) -> bool:
    """Whether a call must go through the custom op: under ``torch.compile``, a dispatch mode (fake tensors, AOT
    autograd's tracing) or a functorch transform (vmap, grad, ...), or with tensor subclasses."""
    if (torch.compiler.is_compiling() or torch._C._len_torch_dispatch_stack() > 0
            or torch._C._functorch.peek_interpreter_stack() is not None):
        return True
    return any(type(a) is not Tensor and isinstance(a, Tensor) and not isinstance(a, torch.nn.Parameter)
               for a in args)


def call(op, *args):
    """Runs one of this module's ops on ``args`` (positional, as its schema).

    Eager calls on plain tensors go through :data:`_EAGER`: the op's own implementation, ``setup_context`` and
    backward in a plain ``torch.autograd.Function`` (the same kernels and the same gradients, bit for bit), which
    saves the custom-op dispatch: per render 0.4 ms of host time forward and 0.7 ms forward + backward on an H200
    machine's host (BENCHMARKS.md, "Fifth GPU round"). Traced calls (:func:`_traced`) go through the op itself, so that
    ``torch.compile`` captures it whole.
    """
    return op(*args) if _traced(args) else _EAGER[op](*args)
