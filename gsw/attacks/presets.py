"""Named attack tables: the paper's set, the official code's set, robustness sweeps, training ranges.

- :data:`IMAGE_ATTACKS` / :data:`MODEL_ATTACKS`: the evaluation attacks by name, at the paper's strengths
  (the defaults of the functions in :mod:`gsw.attacks.ops` and :mod:`gsw.attacks.model`);
  :data:`PAPER_IMAGE_ATTACKS` lists those strengths as keyword arguments (what
  :func:`gsw.attacks.layers.paper_attacks` builds its fixed layers from).
- :data:`OFFICIAL_ATTACKS`: the official code's (mislabelled) settings.
- :data:`SWEEPS`: robustness curves (:func:`sweep`, :func:`sweep_parameter`).
- :data:`VIEW_MODEL_ATTACKS`: model attacks that render the model; :func:`bind_model_attacks` binds them
  to views.
- :data:`TRAINING_RANGES` / :data:`TRAINING_COMBINED_RANGES`: ``(weakest, strongest)`` of the random training
  attacks (:func:`gsw.attacks.layers.training_noise_layers` and :class:`gsw.attacks.layers.GpuAttacks`).

Example:
    >>> from gsw.attacks import presets
    >>> sorted(presets.IMAGE_ATTACKS)
    ['blur', 'brightness', 'combined', 'contrast', 'crop', 'jpeg', 'noise', 'rotation', 'scaling']
    >>> presets.PAPER_IMAGE_ATTACKS["crop"]
    {'keep_area': 0.4}
"""

from __future__ import annotations

import functools
import inspect
from typing import TYPE_CHECKING, Any, Callable, Sequence

from torch import Tensor

from gsw.attacks.model import (clone_random, export_compressed_ply, export_splat, export_spz, finetune,
                               parameter_noise, parameter_noise_attributes, prune_by_opacity, quantize, reduce_sh,
                               remove_random)
from gsw.attacks.ops import (brightness, combined, contrast, crop, gaussian_blur, gaussian_noise, jpeg,
                             official_blur, official_crop, official_jpeg, official_noise, rotation, scaling)
from gsw.gaussians import Gaussians

if TYPE_CHECKING:
    from gsw.camera import Camera

__all__ = [
    "IMAGE_ATTACKS",
    "PAPER_IMAGE_ATTACKS",
    "OFFICIAL_ATTACKS",
    "SWEEPS",
    "sweep",
    "sweep_parameter",
    "MODEL_ATTACKS",
    "VIEW_MODEL_ATTACKS",
    "MODEL_ATTACK_NAMES",
    "EXPORT_MODEL_ATTACKS",
    "bind_model_attacks",
    "TRAINING_RANGES",
    "TRAINING_COMBINED_RANGES",
]

# --------------------------------------------------------------------------------------------- image attacks

#: The paper's fixed-strength image attacks (the defaults of each function, :data:`PAPER_IMAGE_ATTACKS`), plus
#: brightness and contrast (factor 1.5, as in Stable Signature's evaluation); call as ``fn(img)``.
IMAGE_ATTACKS: dict[str, Callable[[Tensor], Tensor]] = {
    "noise": gaussian_noise,
    "rotation": rotation,
    "scaling": scaling,
    "blur": gaussian_blur,
    "crop": crop,
    "jpeg": jpeg,
    "combined": combined,
    "brightness": brightness,
    "contrast": contrast,
}


def _defaults(fn: Callable[..., Any], *names: str) -> dict[str, Any]:
    """The default values of the keyword arguments ``names`` of ``fn``."""
    params = inspect.signature(fn).parameters
    return {name: params[name].default for name in names}


#: The paper's image attacks (3D-GSW, CVPR 2025; ``GUIDE.md`` section 1.7) as keyword arguments of
#: ``IMAGE_ATTACKS[name]``: the strengths are the functions' defaults, read from their signatures so that the
#: numbers are written once (noise sigma 0.1, rotation 30 degrees, scaling 0.75, blur sigma 0.1, crop 40 % of
#: the area, JPEG quality 50, combined = crop + blur + JPEG at those strengths).
PAPER_IMAGE_ATTACKS: dict[str, dict[str, Any]] = {
    "noise": _defaults(gaussian_noise, "sigma"),
    "rotation": _defaults(rotation, "degrees"),
    "scaling": _defaults(scaling, "factor"),
    "blur": _defaults(gaussian_blur, "sigma"),
    "crop": _defaults(crop, "keep_area"),
    "jpeg": _defaults(jpeg, "quality"),
    "combined": _defaults(combined, "keep_area", "blur_sigma", "quality"),
}


#: The official code's attack settings (not the paper's); call as ``fn(img)``.
OFFICIAL_ATTACKS: dict[str, Callable[[Tensor], Tensor]] = {
    "noise": official_noise,
    "blur": official_blur,
    "crop": official_crop,
    "jpeg": official_jpeg,
}

#: Robustness-curve sweeps: attack name -> (keyword of the attack function, values: weakest first; brightness
#: and contrast in increasing factor, 1 being the identity).
SWEEPS: dict[str, tuple[str, tuple[float, ...]]] = {
    "noise": ("sigma", (0.0, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3)),
    "jpeg": ("quality", (90, 70, 50, 30, 20, 10)),
    "blur": ("sigma", (0.1, 0.5, 1.0, 1.5, 2.0, 3.0)),
    "crop": ("keep_area", (1.0, 0.8, 0.6, 0.4, 0.3, 0.2, 0.1)),
    "rotation": ("degrees", (0.0, 5.0, 10.0, 15.0, 30.0, 45.0, 90.0)),
    "scaling": ("factor", (1.0, 0.9, 0.75, 0.5, 0.4, 0.25)),
    "brightness": ("factor", (0.5, 0.75, 1.0, 1.25, 1.5, 2.0)),
    "contrast": ("factor", (0.5, 0.75, 1.0, 1.25, 1.5, 2.0)),
}


def sweep(name: str) -> list:
    """Parameter values for a robustness curve of the attack ``name`` (see :data:`SWEEPS` for the order).

    Use with :func:`sweep_parameter`: ``[IMAGE_ATTACKS[name](img, **{sweep_parameter(name): v}) for v in
    sweep(name)]``.

    Args:
        name: one of ``noise`` (sigma), ``jpeg`` (quality), ``blur`` (sigma), ``crop`` (keep_area),
            ``rotation`` (degrees), ``scaling``, ``brightness``, ``contrast`` (factor).

    Returns:
        A new list of values.
    """
    if name not in SWEEPS:
        raise KeyError(f"no sweep for {name!r}; choose from {sorted(SWEEPS)}")
    return list(SWEEPS[name][1])


def sweep_parameter(name: str) -> str:
    """Keyword argument of ``IMAGE_ATTACKS[name]`` that :func:`sweep` varies.

    Args:
        name: a key of :data:`SWEEPS`.

    Returns:
        The keyword name.
    """
    if name not in SWEEPS:
        raise KeyError(f"no sweep for {name!r}; choose from {sorted(SWEEPS)}")
    return SWEEPS[name][0]


# --------------------------------------------------------------------------------------------- model attacks

#: Model attacks at the paper's strengths (plus the extra ones at their defaults); call as ``fn(g)``.
MODEL_ATTACKS: dict[str, Callable[[Gaussians], Gaussians]] = {
    "parameter_noise": parameter_noise,
    "parameter_noise_attributes": parameter_noise_attributes,
    "remove": remove_random,
    "clone": clone_random,
    "reduce_sh": reduce_sh,
    "prune_by_opacity": prune_by_opacity,
    "quantize": quantize,
    "export_splat": export_splat,
    "export_spz": export_spz,
    "export_compressed_ply": export_compressed_ply,
}

#: What leaving for a viewer does to a model: SH stripped to degree 0, ``.splat`` and ``.spz`` export and
#: reload through the real codecs, 8-bit quantisation of every attribute, PlayCanvas compressed PLY.
EXPORT_MODEL_ATTACKS: tuple[str, ...] = ("reduce_sh", "export_splat", "export_spz", "quantize",
                                         "export_compressed_ply")

#: Model attacks that render the model, at their defaults; call as ``fn(g, cameras, background=bg)``
#: (:func:`bind_model_attacks` turns them into ``fn(g)``).
VIEW_MODEL_ATTACKS: dict[str, Callable[..., Gaussians]] = {
    "finetune": finetune,
}

#: A model attack bound to everything but the model.
ModelAttack = Callable[[Gaussians], Gaussians]

#: Every model attack name (:data:`MODEL_ATTACKS` and :data:`VIEW_MODEL_ATTACKS`).
MODEL_ATTACK_NAMES: tuple[str, ...] = (*MODEL_ATTACKS, *VIEW_MODEL_ATTACKS)


def bind_model_attacks(names: Sequence[str], cameras: Sequence["Camera"],
                       background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> dict[str, ModelAttack]:
    """Model attacks by name, as ``fn(g)``: those of :data:`VIEW_MODEL_ATTACKS` bound to ``cameras``.

    Args:
        names: keys of :data:`MODEL_ATTACKS` or :data:`VIEW_MODEL_ATTACKS`.
        cameras: the views a view attack renders (e.g. the embedding views).
        background: their render background.

    Returns:
        name -> attack.
    """
    unknown = [n for n in names if n not in MODEL_ATTACK_NAMES]
    if unknown:
        raise KeyError(f"unknown model attacks {unknown}; choose from {list(MODEL_ATTACK_NAMES)}")
    return {n: MODEL_ATTACKS[n] if n in MODEL_ATTACKS else
            functools.partial(VIEW_MODEL_ATTACKS[n], cameras=list(cameras), background=tuple(background))
            for n in names}

# --------------------------------------------------------------------------------------------- training ranges

#: Ranges ``(weakest, strongest)`` of the random training attacks (decoder pre-training, train-time attack
#: sampling); a draw is ``weakest + t (strongest - weakest)`` with ``t ~ U(0, strength)``. Units: ``crop``
#: fraction of the area kept, ``resize`` scale factor, ``jpeg`` quality, ``blur`` sigma in pixels, ``noise``
#: standard deviation, ``rotation`` degrees (random sign).
TRAINING_RANGES: dict[str, tuple[float, float]] = {
    "crop": (1.0, 0.35),
    "resize": (1.0, 0.5),
    "jpeg": (90.0, 50.0),
    "blur": (0.1, 2.0),
    "noise": (0.0, 0.08),
    "rotation": (0.0, 15.0),
}

#: Ranges of the training ``combined`` attack (crop, then blur, then JPEG), milder than each alone.
TRAINING_COMBINED_RANGES: dict[str, tuple[float, float]] = {
    "crop": (1.0, 0.5),
    "blur": (0.1, 1.0),
    "jpeg": (90.0, 60.0),
}
