"""gsplat-compatible functional entry point: :func:`rasterization`, a drop-in for ``gsplat.rasterization`` (1.5.3).

It takes gsplat's arguments (activated scales and opacities, batched ``viewmats [C, 4, 4]`` / ``Ks [C, 3, 3]``),
returns gsplat's ``(render_colors [C, H, W, D], render_alphas [C, H, W, 1], meta)`` and fills ``meta`` with the
keys gsplat's densification strategies read (``means2d`` carrying the screen-space gradient, ``radii``,
``gaussian_ids``, ``width``, ``height``, ``n_cameras``, ...). It runs gsw's kernels
(:func:`gsw.render.rasterize.project` and :func:`gsw.render.rasterize.blend`), so it works on the CPU too.

How gsplat's options map onto gsw's kernels:

* ``near_plane`` / ``far_plane``: the kernels cull at the fixed ``gsw.constants["NEAR_PLANE"]``; another near
  plane is met exactly by rendering the scene scaled by ``NEAR_PLANE / near_plane`` about the camera centre
  (pixel positions, footprints and colours are invariant under that scaling; depths are scaled back). Gaussians
  at or beyond ``far_plane`` get radius 0.
* ``eps2d``: the kernels dilate the 2-D covariance by ``COV2D_DILATION`` (0.3, gsplat's default); other values
  raise NotImplementedError. ``rasterize_mode="antialiased"`` multiplies the opacities by gsplat's compensation
  ``sqrt(det(cov2d) / det(cov2d + eps2d I))``, computed from the dilated conic.
* ``radius_clip``: Gaussians whose pixel radius is ``<= radius_clip`` are culled. gsw has one radius per
  Gaussian (a circle); ``meta["radii"]`` repeats it for gsplat's ``[..., 2]`` (x, y) layout.
* ``render_mode`` ``"D"``, ``"ED"``, ``"RGB+D"``, ``"RGB+ED"``: the blending kernel outputs the accumulated depth
  ``sum_i w_i z_i`` next to the colour (no background on that channel, as in gsplat); ``ED`` divides it by
  ``alpha.clamp(min=1e-10)`` as gsplat does.
* ``packed``: both layouts are supported; with ``packed=True`` the per-(camera, Gaussian) meta entries hold the
  visible pairs only (``camera_ids``, ``gaussian_ids``, ``means2d [nnz, 2]``...), with ``packed=False`` they are
  ``[C, N, ...]`` and ``gaussian_ids`` is None. The images are the same either way.
* ``tile_size``, ``channel_chunk``, ``segmented``: accepted; they only change how gsplat schedules its work
  (gsw's tiles are always ``gsw.constants["TILE_SIZE"]`` pixels and colours are blended 3 channels at a time).
* Colours with ``D != 3`` channels (``sh_degree=None``) are blended in groups of 3 channels.

Anything gsw's kernels cannot do (``absgrad``, ``sparse_grad``, ``distributed``, cameras other than
``"pinhole"``, ``covars``, unscented transforms, distortion, rolling shutter, leading batch dimensions, SH degree
above 3, gradients w.r.t. ``viewmats`` / ``Ks``) raises NotImplementedError naming the keyword and its value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from gsw.render.rasterize import Projection, blend, project

__all__ = ["rasterization"]

_RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
_RASTERIZE_MODES = ("classic", "antialiased")


def _constants() -> dict[str, Any]:
    from gsw.constants import COV2D_DILATION, MAX_SH_DEGREE, NEAR_PLANE, TILE_SIZE  # noqa: PLC0415

    return {"COV2D_DILATION": COV2D_DILATION, "MAX_SH_DEGREE": MAX_SH_DEGREE, "NEAR_PLANE": NEAR_PLANE,
            "TILE_SIZE": TILE_SIZE}


def _unsupported(keyword: str, value: Any, why: str = "") -> NotImplementedError:
    return NotImplementedError(f"gsw.rasterization: {keyword}={value!r} is not supported by gsw's kernels"
                               + (f" ({why})" if why else ""))


def _check_options(opts: dict[str, Any]) -> None:
    """Raises NotImplementedError naming the first gsplat option gsw cannot honour, ValueError for bad values."""
    c = _constants()
    if opts["render_mode"] not in _RENDER_MODES:
        raise ValueError(f"render_mode must be one of {_RENDER_MODES}, got {opts['render_mode']!r}")
    if opts["rasterize_mode"] not in _RASTERIZE_MODES:
        raise ValueError(f"rasterize_mode must be one of {_RASTERIZE_MODES}, got {opts['rasterize_mode']!r}")
    if not (isinstance(opts["near_plane"], (int, float)) and opts["near_plane"] > 0):
        raise ValueError(f"near_plane must be a positive number, got {opts['near_plane']!r}")
    if not opts["far_plane"] > opts["near_plane"]:
        raise ValueError(f"far_plane must be above near_plane, got {opts['far_plane']!r} <= {opts['near_plane']!r}")
    if not math.isclose(float(opts["eps2d"]), c["COV2D_DILATION"], rel_tol=1e-6):
        raise _unsupported("eps2d", opts["eps2d"], f"the kernels dilate by {c['COV2D_DILATION']}")
    flags = {"sparse_grad": "no sparse gradients", "absgrad": "the blending kernel returns summed gradients only",
             "distributed": "single-process only", "with_ut": "no unscented transform",
             "with_eval3d": "no 3-D evaluation"}
    for name, why in flags.items():
        if opts[name]:
            raise _unsupported(name, opts[name], why)
    if opts["camera_model"] != "pinhole":
        raise _unsupported("camera_model", opts["camera_model"], "pinhole cameras only")
    for name in ("covars", "radial_coeffs", "tangential_coeffs", "thin_prism_coeffs", "ftheta_coeffs",
                 "viewmats_rs"):
        if opts[name] is not None:
            raise _unsupported(name, "a value", "only None is supported")
    rs = opts["rolling_shutter"]
    if rs is not None and str(getattr(rs, "name", rs)).upper() != "GLOBAL":
        raise _unsupported("rolling_shutter", rs, "global shutter only")
    sh = opts["sh_degree"]
    if sh is not None and not 0 <= int(sh) <= c["MAX_SH_DEGREE"]:
        if int(sh) > c["MAX_SH_DEGREE"]:
            raise _unsupported("sh_degree", sh, f"SH degrees 0..{c['MAX_SH_DEGREE']}")
        raise ValueError(f"sh_degree must be >= 0 or None, got {sh!r}")


def _check_shapes(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
                  viewmats: Tensor, Ks: Tensor, sh_degree: int | None) -> tuple[int, int]:
    """Validates gsplat's (unbatched) shapes; returns (C, N)."""
    if means.dim() != 2:
        raise _unsupported("means", f"shape {list(means.shape)}", "leading batch dimensions; pass [N, 3]")
    n = means.shape[0]
    for name, t, shape in (("means", means, (n, 3)), ("quats", quats, (n, 4)), ("scales", scales, (n, 3)),
                           ("opacities", opacities, (n,))):
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {list(t.shape)}")
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4) or Ks.dim() != 3 or Ks.shape[1:] != (3, 3) \
            or viewmats.shape[0] != Ks.shape[0]:
        raise ValueError(f"viewmats [C, 4, 4] and Ks [C, 3, 3] must agree, got {list(viewmats.shape)} and "
                         f"{list(Ks.shape)}")
    c = viewmats.shape[0]
    if torch.is_grad_enabled() and (viewmats.requires_grad or Ks.requires_grad):
        raise _unsupported("viewmats/Ks", "tensors requiring grad", "no camera gradients; detach them")
    if sh_degree is None:
        ok = (colors.dim() == 2 and colors.shape[0] == n) or (colors.dim() == 3 and colors.shape[:2] == (c, n))
        want = f"[{n}, D] or [{c}, {n}, D]"
    else:
        ok = colors.shape[-1] == 3 and ((colors.dim() == 3 and colors.shape[0] == n)
                                        or (colors.dim() == 4 and colors.shape[:2] == (c, n)))
        ok = ok and (int(sh_degree) + 1) ** 2 <= colors.shape[-2]
        want = f"[{n}, K, 3] or [{c}, {n}, K, 3] with K >= {(int(sh_degree) + 1) ** 2}"
    if not ok:
        raise ValueError(f"colors must have shape {want}, got {list(colors.shape)}")
    return c, n


@dataclass
class _Views:
    """Per-camera projections stacked over the C cameras (all [C, N, ...] graph tensors)."""

    radii: Tensor
    means2d: Tensor
    conics: Tensor
    depths: Tensor
    colors: Tensor | None  # [C, N, 3] SH colours, None with direct colours


def _project_all(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
                 viewmats: Tensor, Ks: Tensor, width: int, height: int, sh_degree: int | None,
                 near_plane: float) -> _Views:
    """Projects into every camera, scaled by NEAR_PLANE / near_plane about each camera centre (see module doc)."""
    from gsw.camera import Camera  # noqa: PLC0415  (camera imports nothing from gsw.render)

    s = _constants()["NEAR_PLANE"] / float(near_plane)
    means_s = means * s if s != 1.0 else means
    log_scales = torch.log(scales) + math.log(s)
    # The blending stage takes the activated opacities themselves; their logits only size the footprints.
    logits = torch.logit(opacities.detach())
    dummy = means.new_zeros(means.shape[0], 3) if sh_degree is None else None
    outs: list[Projection] = []
    for ci in range(viewmats.shape[0]):
        vm = viewmats[ci].detach().clone()
        vm[:3, 3] *= s
        K = Ks[ci].detach().double().cpu()
        cam = Camera(viewmat=vm, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                     width=int(width), height=int(height))
        if sh_degree is None:
            sh, degree = dummy, -1
        else:
            sh, degree = (colors[ci] if colors.dim() == 4 else colors), int(sh_degree)
        outs.append(project(means_s, quats, log_scales, logits, sh.to(means.dtype), cam, degree))
    depths = torch.stack([p.depths for p in outs])
    return _Views(radii=torch.stack([p.radii for p in outs]), means2d=torch.stack([p.means2d for p in outs]),
                  conics=torch.stack([p.conics for p in outs]), depths=depths / s if s != 1.0 else depths,
                  colors=None if sh_degree is None else torch.stack([p.colors for p in outs]))


def _compensation(conics: Tensor, eps2d: float) -> Tensor:
    """gsplat's antialiasing factor ``sqrt(det(S) / det(S + eps I))`` from the conic of the dilated ``S + eps I``.

    With conic ``(a, b, c)`` the inverse of ``S + eps I``: ``det(S) / det(S + eps I) = 1 - eps (a + c) +
    eps^2 (a c - b^2)``.
    """
    a, b, c = conics.unbind(-1)
    ratio = 1.0 - eps2d * (a + c) + eps2d * eps2d * (a * c - b * b)
    return torch.sqrt(ratio.clamp_min(torch.finfo(conics.dtype).tiny))


def _color_chunks(colors: Tensor, backgrounds: Tensor | None, c: int, n: int
                  ) -> tuple[list[Tensor], list[Tensor]]:
    """Direct colours [N, D] / [C, N, D] as ceil(D/3) chunks [C, N, 3] (zero-padded) and backgrounds [C, 3]."""
    d = colors.shape[-1]
    cols = colors if colors.dim() == 3 else colors.unsqueeze(0).expand(c, n, d)
    bgs = backgrounds if backgrounds is not None else colors.new_zeros(c, d)
    pad = (-d) % 3
    if pad:
        cols = torch.cat([cols, cols.new_zeros(c, n, pad)], dim=-1)
        bgs = torch.cat([bgs, bgs.new_zeros(c, pad)], dim=-1)
    return list(cols.split(3, dim=-1)), list(bgs.split(3, dim=-1))


def _meta(views: _Views, means2d: Tensor, opac: Tensor, packed: bool, width: int, height: int,
          tile_size: int) -> dict[str, Any]:
    """gsplat's meta dictionary (see :func:`rasterization`)."""
    c = views.radii.shape[0]
    tile = _constants()["TILE_SIZE"]
    radii2 = views.radii.unsqueeze(-1).expand(*views.radii.shape, 2)
    meta: dict[str, Any] = {"batch_ids": None, "camera_ids": None, "gaussian_ids": None, "means2d": means2d,
                            "radii": radii2, "depths": views.depths, "conics": views.conics, "opacities": opac}
    if packed:
        cam_ids, g_ids = torch.nonzero(views.radii > 0, as_tuple=True)
        meta.update(batch_ids=torch.zeros_like(cam_ids), camera_ids=cam_ids, gaussian_ids=g_ids,
                    radii=radii2[cam_ids, g_ids], depths=views.depths[cam_ids, g_ids],
                    conics=views.conics[cam_ids, g_ids], opacities=opac[cam_ids, g_ids])
    meta.update(width=int(width), height=int(height), tile_size=int(tile_size), gsw_tile_size=tile,
                tile_width=-(-int(width) // tile), tile_height=-(-int(height) // tile), n_batches=1, n_cameras=c,
                packed=bool(packed))
    return meta


def _screen_means(views: _Views, packed: bool) -> tuple[Tensor, Tensor]:
    """(means2d fed to the blending [C, N, 2], the meta's means2d): the meta tensor is on the gradient path."""
    if not packed:
        return views.means2d, views.means2d
    cam_ids, g_ids = torch.nonzero(views.radii > 0, as_tuple=True)
    m_packed = views.means2d[cam_ids, g_ids]  # [nnz, 2]
    full = torch.zeros_like(views.means2d).index_put((cam_ids, g_ids), m_packed)
    return full, m_packed


def _blend_views(views: _Views, means2d: Tensor, opac: Tensor, chunks: list[Tensor], bgs: list[Tensor], d: int,
                 render_mode: str, width: int, height: int) -> tuple[Tensor, Tensor]:
    """Blends every camera: colour chunks [C, N, 3] on backgrounds [C, 3], then the depth channel of
    ``render_mode``. Returns (render_colors [C, H, W, D'], render_alphas [C, H, W, 1])."""
    images, alphas = [], []
    for ci in range(views.radii.shape[0]):
        planes, alpha, depth = [], None, None
        for col, bg in zip(chunks, bgs):
            proj = Projection(means2d[ci], views.conics[ci], views.depths[ci], col[ci], opac[ci], views.radii[ci])
            image, a, z, _, _ = blend(proj, width, height, bg[ci].to(means2d.dtype))
            planes.append(image)
            alpha, depth = (a, z) if alpha is None else (alpha, depth)
        out = torch.cat(planes)[:d]
        if render_mode in ("D", "RGB+D"):
            out = torch.cat([out, depth])
        elif render_mode in ("ED", "RGB+ED"):
            out = torch.cat([out, depth / alpha.clamp(min=1e-10)])
        images.append(out.permute(1, 2, 0))
        alphas.append(alpha.permute(1, 2, 0))
    return torch.stack(images), torch.stack(alphas)


def rasterization(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
                  viewmats: Tensor, Ks: Tensor, width: int, height: int, near_plane: float = 0.01,
                  far_plane: float = 1e10, radius_clip: float = 0.0, eps2d: float = 0.3,
                  sh_degree: int | None = None, packed: bool = True, tile_size: int = 16,
                  backgrounds: Tensor | None = None, render_mode: str = "RGB", sparse_grad: bool = False,
                  absgrad: bool = False, rasterize_mode: str = "classic", channel_chunk: int = 32,
                  distributed: bool = False, camera_model: str = "pinhole", segmented: bool = False,
                  covars: Tensor | None = None, with_ut: bool = False, with_eval3d: bool = False,
                  radial_coeffs: Tensor | None = None, tangential_coeffs: Tensor | None = None,
                  thin_prism_coeffs: Tensor | None = None, ftheta_coeffs: Any = None, rolling_shutter: Any = None,
                  viewmats_rs: Tensor | None = None) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Drop-in for ``gsplat.rasterization`` (1.5.3) on gsw's kernels; see the module docstring for each option.

    Args:
        means: [N, 3] world positions.
        quats: [N, 4] rotations (w, x, y, z), unnormalised.
        scales: [N, 3] activated (linear) scales.
        opacities: [N] activated opacities in [0, 1].
        colors: [N, K, 3] or [C, N, K, 3] SH coefficients when ``sh_degree`` is given, else [N, D] or [C, N, D]
            colours (any D).
        viewmats: [C, 4, 4] world-to-camera matrices (OpenCV axes).
        Ks: [C, 3, 3] intrinsics (fx, fy, cx, cy are read).
        width: image width.
        height: image height.
        near_plane, far_plane, radius_clip, eps2d, sh_degree, packed, tile_size, backgrounds, render_mode,
        sparse_grad, absgrad, rasterize_mode, channel_chunk, distributed, camera_model, segmented, covars,
        with_ut, with_eval3d, radial_coeffs, tangential_coeffs, thin_prism_coeffs, ftheta_coeffs,
        rolling_shutter, viewmats_rs: gsplat's options (``backgrounds``: [C, D]).

    Returns:
        ``(render_colors [C, H, W, D'], render_alphas [C, H, W, 1], meta)`` with D' = D, D + 1 (``RGB+D`` /
        ``RGB+ED``) or 1 (``D`` / ``ED``). ``meta``: ``means2d`` ([C, N, 2], or [nnz, 2] packed; call
        ``retain_grad()`` before backward to read the screen-space gradient), ``radii`` ([C, N, 2] or [nnz, 2]
        int32), ``depths``, ``conics``, ``opacities`` (after the antialiasing compensation), ``batch_ids`` /
        ``camera_ids`` / ``gaussian_ids`` (None unless packed), ``width``, ``height``, ``tile_size``,
        ``tile_width``, ``tile_height``, ``n_batches``, ``n_cameras``, ``packed``.

    Raises:
        NotImplementedError: an option value gsw's kernels cannot honour (named in the message).
        ValueError: malformed shapes or values.
    """
    opts = dict(near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree,
                render_mode=render_mode, sparse_grad=sparse_grad, absgrad=absgrad, rasterize_mode=rasterize_mode,
                distributed=distributed, camera_model=camera_model, covars=covars, with_ut=with_ut,
                with_eval3d=with_eval3d, radial_coeffs=radial_coeffs, tangential_coeffs=tangential_coeffs,
                thin_prism_coeffs=thin_prism_coeffs, ftheta_coeffs=ftheta_coeffs, rolling_shutter=rolling_shutter,
                viewmats_rs=viewmats_rs)
    _check_options(opts)
    c, n = _check_shapes(means, quats, scales, opacities, colors, viewmats, Ks, sh_degree)
    rgb = render_mode in ("RGB", "RGB+D", "RGB+ED")
    d = (3 if sh_degree is not None else colors.shape[-1]) if rgb else 0
    if backgrounds is not None and rgb and tuple(backgrounds.shape) != (c, d):
        raise ValueError(f"backgrounds must have shape [{c}, {d}], got {list(backgrounds.shape)}")
    views = _project_all(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                         near_plane)
    views.radii = torch.where((views.depths >= far_plane) | (views.radii <= radius_clip), 0, views.radii)
    opac = opacities.unsqueeze(0).expand(c, n)
    if rasterize_mode == "antialiased":
        opac = opac * _compensation(views.conics, float(eps2d))
    m2d_blend, m2d_meta = _screen_means(views, packed)
    if not rgb:
        chunks, bgs = [means.new_zeros(c, n, 3)], [means.new_zeros(c, 3)]
    elif sh_degree is not None:
        chunks, bgs = [views.colors], [backgrounds if backgrounds is not None else means.new_zeros(c, 3)]
    else:
        chunks, bgs = _color_chunks(colors.to(means.dtype), backgrounds, c, n)
    images, alphas = _blend_views(views, m2d_blend, opac, chunks, bgs, d, render_mode, width, height)
    return images, alphas, _meta(views, m2d_meta, opac, packed, width, height, tile_size)
