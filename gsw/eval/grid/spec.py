"""What a grid computes: the named methods (:data:`METHODS`, EmbedConfig overrides) and :class:`GridSpec`."""

from __future__ import annotations

import dataclasses
import itertools
import json
from dataclasses import asdict, dataclass, field
from typing import Any, Iterable, NamedTuple, Sequence

from gsw.attacks.presets import EXPORT_MODEL_ATTACKS, IMAGE_ATTACKS, MODEL_ATTACK_NAMES, SWEEPS
from gsw.mark.embed import PAPER_RECIPE, EmbedConfig, apply_overrides
from gsw.stats import DETECTION_FPR

__all__ = ["ABLATIONS", "FORMAT", "METHODS", "PAPER_MODEL_ATTACKS", "Cell", "GridMismatchError", "GridSpec",
           "apply_overrides", "lpips_loss_overrides", "method_config"]

#: Named methods as :class:`~gsw.mark.embed.EmbedConfig` overrides (``"weights"`` overrides single fields of
#: :class:`~gsw.mark.loss.LossWeights`). The two baselines are the prior methods ported to this embedder: no FGD
#: and no wavelet-subband loss, with StegaNeRF's magnitude mask (no exponential) or no mask (WateRF).
#: ``3d-gsw+attacks`` decodes an attacked copy of the render at half of the fine-tuning steps;
#: ``3d-gsw+all-attacks`` also decodes the render of a perturbed model (parameter noise or SH degree 0) at
#: half of them (``EmbedConfig.model_attacks``). ``3d-gsw`` / ``paper`` and every method derived from them pin
#: the paper-faithful recipe (:data:`gsw.mark.embed.PAPER_RECIPE`: given cameras only, exponential mask, no
#: train-time attacks, the L1 image term) whatever the defaults; ``default`` is the library's default
#: (``EmbedConfig()``, which is ``freeze-rest+views`` without FGD and with the squared-error image term); ``wild``
#: (issue 23) trains on sampled viewpoints and render sizes, with image attacks up to the evaluation's strengths and
#: every model distortion (parameter noise, SH degree 0, ``.splat`` / ``.spz`` / 8-bit exports). ``freeze-rest`` keeps the SH rest coefficients fixed
#: and updates the others without the exponential mask, so the mark lives where SH-degree-0 viewers and ``.splat``
#: keep it (the mask would all but freeze saturated DC colours); ``freeze-rest+views`` also renders every step from a
#: fresh viewpoint sampled around the content (:mod:`gsw.mark.views`).
_PAPER_NO_SUBBAND = {**PAPER_RECIPE["weights"], "subband": 0.0}  # the paper's image term, no subband loss
METHODS: dict[str, dict[str, Any]] = {
    "default": {},
    "3d-gsw": dict(PAPER_RECIPE),
    "paper": dict(PAPER_RECIPE),
    "freeze-rest": {**PAPER_RECIPE, "freeze": ("f_rest",), "mask": "none"},
    "freeze-rest+views": {**PAPER_RECIPE, "freeze": ("f_rest",), "mask": "none", "novel_views": 1.0},
    "wild": {**PAPER_RECIPE, "novel_views": 0.5, "render_scales": (0.5, 2.0), "attacks": 0.5,
             "attack_ranges": "matched", "model_attacks": 0.5,
             "model_attack_kinds": ("noise", "sh0", "splat", "spz", "8bit")},
    "no-fgd": {**PAPER_RECIPE, "fgd": False},
    "no-mask": {**PAPER_RECIPE, "mask": "none"},
    "no-subband": {**PAPER_RECIPE, "weights": _PAPER_NO_SUBBAND},
    "stega-3dgs": {**PAPER_RECIPE, "fgd": False, "mask": "stega", "weights": _PAPER_NO_SUBBAND},
    "waterf-3dgs": {**PAPER_RECIPE, "fgd": False, "mask": "none", "weights": _PAPER_NO_SUBBAND},
    "3d-gsw+attacks": {**PAPER_RECIPE, "attacks": 0.5},
    "3d-gsw+all-attacks": {**PAPER_RECIPE, "attacks": 0.5, "model_attacks": 0.5},
}

#: Rows of the ablation table: the full method and one component off at a time.
ABLATIONS: tuple[str, ...] = ("3d-gsw", "no-fgd", "no-mask", "no-subband")

#: The paper's model attacks (Gaussian noise on the parameters, remove 20 %, clone 20 %).
PAPER_MODEL_ATTACKS: tuple[str, ...] = ("parameter_noise", "remove", "clone")
#: The grid's default model attacks: the paper's and the exports (:data:`gsw.attacks.presets.EXPORT_MODEL_ATTACKS`).
GRID_MODEL_ATTACKS: tuple[str, ...] = PAPER_MODEL_ATTACKS + EXPORT_MODEL_ATTACKS

#: EmbedConfig fields set by the grid itself (a grid axis or the scene), not by overrides.
_GRID_FIELDS = frozenset({"epochs", "seed", "background"})
_LPIPS_NETS = (None, "vgg", "alex")
#: Version of the cell / grid file layout.
FORMAT = 1


class GridMismatchError(ValueError):
    """The output folder holds a grid with other settings or another scene."""


def lpips_loss_overrides(net: str | None) -> dict[str, Any]:
    """EmbedConfig overrides for the LPIPS term of the embedding loss.

    Args:
        net: ``"vgg"`` or ``"alex"``, or None to drop the term (network off and weight 0).

    Returns:
        Overrides for :attr:`GridSpec.embed`.
    """
    return {"lpips_net": net} if net else {"lpips_net": None, "weights": {"lpips": 0.0}}


def method_config(method: str, base: EmbedConfig | None = None) -> EmbedConfig:
    """The :class:`EmbedConfig` of a named method.

    Args:
        method: a key of :data:`METHODS`.
        base: configuration the method's overrides apply to (default: ``EmbedConfig()``).

    Returns:
        A new :class:`EmbedConfig`.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose from {list(METHODS)}")
    return apply_overrides(base or EmbedConfig(), METHODS[method])



class Cell(NamedTuple):
    """One grid cell."""

    method: str
    bits: int
    seed: int

    @property
    def name(self) -> str:
        """File stem of the cell, e.g. ``3d-gsw_32b_seed0``."""
        return f"{self.method}_{self.bits}b_seed{self.seed}"


def _selection(name: str, values: Iterable, known: Iterable | None = None) -> tuple:
    values = tuple(values)
    if known is not None:
        known = list(known)
        unknown = [v for v in values if v not in known]
        if unknown:
            raise ValueError(f"unknown {name} {unknown}; choose from {list(known)}")
    if len(set(values)) != len(values):
        raise ValueError(f"duplicate {name} in {list(values)}")
    return values


def _nonempty(name: str, values: tuple) -> tuple:
    if not values:
        raise ValueError(f"no {name} selected")
    return values


@dataclass
class GridSpec:
    """What :func:`run_grid` computes (defaults: the paper's grid, every method at 32, 48 and 64 bits).

    Attributes:
        methods: keys of :data:`METHODS`.
        bits: message lengths (32, 48, 64 with the shipped decoders).
        seeds: seeds of the message, view order and train-time attacks.
        epochs: embedding epochs.
        image_attacks: keys of :data:`gsw.attacks.ops.IMAGE_ATTACKS` (the paper's strengths).
        model_attacks: keys of :data:`gsw.attacks.ops.MODEL_ATTACKS` or :data:`gsw.attacks.ops.VIEW_MODEL_ATTACKS`
            (``finetune`` trains on renders of the embedding views).
        sweeps: keys of :data:`gsw.attacks.ops.SWEEPS`: robustness curves over their values.
        embed: further EmbedConfig overrides for every method (``"weights"`` as a dict), applied before the
            method's own; ``epochs``, ``seed`` and ``background`` are set by the grid.
        fpr: false-positive rate of a detection.
        lpips_net: LPIPS network of the invisibility metric, or None to skip it.
        fps_repeats: passes over the evaluation views when timing renders.
    """

    methods: tuple[str, ...] = tuple(METHODS)
    bits: tuple[int, ...] = (32, 48, 64)
    seeds: tuple[int, ...] = (0, 1, 2)
    epochs: int = 8
    image_attacks: tuple[str, ...] = tuple(IMAGE_ATTACKS)
    model_attacks: tuple[str, ...] = GRID_MODEL_ATTACKS
    sweeps: tuple[str, ...] = tuple(SWEEPS)
    embed: dict[str, Any] = field(default_factory=dict)
    fpr: float = DETECTION_FPR
    lpips_net: str | None = "vgg"
    fps_repeats: int = 1

    def __post_init__(self) -> None:
        self.methods = _nonempty("methods", _selection("methods", self.methods, METHODS))
        self.bits = _nonempty("bit lengths", _selection("bit lengths", self.bits))
        self.seeds = _nonempty("seeds", _selection("seeds", self.seeds))
        self.image_attacks = _selection("image attacks", self.image_attacks, IMAGE_ATTACKS)
        self.model_attacks = _selection("model attacks", self.model_attacks, MODEL_ATTACK_NAMES)
        self.sweeps = _selection("sweeps", self.sweeps, SWEEPS)
        for name, value in (("bits", self.bits), ("seeds", self.seeds), ("epochs", (self.epochs,)),
                            ("fps_repeats", (self.fps_repeats,))):
            if any(not isinstance(v, int) or isinstance(v, bool) for v in value):
                raise ValueError(f"{name} must be integers, got {list(value)}")
        if min(self.bits) <= 0 or self.epochs <= 0 or self.fps_repeats <= 0:
            raise ValueError("bits, epochs and fps_repeats must be positive")
        if not 0.0 < self.fpr < 1.0:
            raise ValueError(f"fpr must be in (0, 1), got {self.fpr}")
        if self.lpips_net not in _LPIPS_NETS:
            raise ValueError(f"lpips_net must be one of {_LPIPS_NETS}, got {self.lpips_net!r}")
        if set(self.embed) & _GRID_FIELDS:
            raise ValueError(f"embed overrides cannot set {sorted(set(self.embed) & _GRID_FIELDS)} "
                             "(the grid sets them)")
        for method in self.methods:
            cfg = self.config(method, 0)
            if cfg.lpips_net is None and cfg.weights.lpips != 0:
                raise ValueError(f"method {method}: lpips_net is None but the LPIPS loss weight is "
                                 f"{cfg.weights.lpips}; also override weights.lpips = 0")

    def cells(self) -> list[Cell]:
        """Every (method, bits, seed), method-major."""
        return [Cell(*c) for c in itertools.product(self.methods, self.bits, self.seeds)]

    def config(self, method: str, seed: int, background: Sequence[float] = (0.0, 0.0, 0.0)) -> EmbedConfig:
        """The EmbedConfig of a cell: :attr:`embed` overrides, then the method's, then epochs, seed, background."""
        base = apply_overrides(EmbedConfig(), self.embed)
        return dataclasses.replace(method_config(method, base), epochs=self.epochs, seed=seed,
                                   background=tuple(float(v) for v in background))

    def settings(self) -> dict[str, Any]:
        """Everything that changes a cell's result, as plain JSON (all fields but methods, bits, seeds)."""
        d = asdict(self)
        for axis in ("methods", "bits", "seeds"):
            del d[axis]
        return json.loads(json.dumps(d))

    @property
    def report_bits(self) -> int:
        """Bit length of the robustness, ablation and detection tables: 32 when in the grid (paper)."""
        return 32 if 32 in self.bits else self.bits[0]
