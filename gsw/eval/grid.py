"""The evaluation grid: watermarking methods x message lengths x seeds, resumable, in the paper's tables.

The compared methods are configurations of the one embedder (:func:`gsw.mark.embed.embed`): :data:`METHODS`
maps a name to :class:`~gsw.mark.embed.EmbedConfig` overrides. :func:`run_grid` embeds every
``(method, bits, seed)`` cell of a :class:`GridSpec` into a :class:`GridScene` (the seed drives the message,
the view order and the train-time attacks), evaluates it on held-out views with
:func:`gsw.eval.report.evaluate_watermark` (PSNR/SSIM/LPIPS against the original renders, bit accuracy and
per-view p-values clean and under every attack, for the watermarked and for the original model) and adds
time, render speed and storage. The output folder holds::

    grid.json                            settings and scene (a rerun with others is refused)
    original.png                         the original model's render of the first evaluation view
    cells/<method>_<bits>b_seed<seed>.json   one cell, written atomically (the completion mark)
    cells/<method>_<bits>b_seed<seed>.png    the watermarked render of the first evaluation view
    summary.json, summary.md             mean +- std over seeds and the paper's tables

A rerun skips the cells whose JSON exists (resumable) and recomputes a corrupt one. ``grid.json`` stores
everything that changes a cell's result (attacks, epochs, embedding overrides, FPR, scene) but not the
methods / bits / seeds selection, so a grid can be extended with more cells in the same folder.

Detection: a view is detected when its binomial p-value (:func:`gsw.stats.binomial_p_value`) is at most
the FPR (1e-6 by default, i.e. at least :func:`gsw.stats.false_positive_threshold` matching
bits). The true-positive rate (TPR) is the share of watermarked views detected, the empirical false-positive
rate (FPR) the share of the original model's views detected for the same message; both clean and per attack.

Example:
    >>> spec = GridSpec(methods=("3d-gsw", "no-fgd"), bits=(32,), seeds=(0, 1), epochs=1)
    >>> [c.name for c in spec.cells()]
    ['3d-gsw_32b_seed0', '3d-gsw_32b_seed1', 'no-fgd_32b_seed0', 'no-fgd_32b_seed1']
    >>> method_config("no-subband").weights.subband
    0.0
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, NamedTuple, Sequence

import torch
from torch import Tensor

from gsw._atomic import atomic_write
from gsw.attacks.presets import IMAGE_ATTACKS, MODEL_ATTACK_NAMES, SWEEPS, bind_model_attacks
from gsw.camera import Camera
from gsw.mark.embed import EmbedConfig, embed
from gsw.mark.loss import lpips_weights
from gsw.eval.report import evaluate_watermark
from gsw.stats import DETECTION_FPR
from gsw.gaussians import Gaussians
from gsw.progress import Progress
from gsw.render.rasterize import rasterize

__all__ = [
    "METHODS", "ABLATIONS", "PAPER_MODEL_ATTACKS", "GridSpec", "GridScene", "Cell", "Stat", "GridSummary",
    "GridMismatchError", "method_config", "apply_overrides", "lpips_loss_overrides", "default_grid_scene",
    "load_grid_scene", "detection_rate", "detection_rates", "mean_std", "cell_metrics", "aggregate", "run_cell",
    "run_grid", "decoder_fingerprint",
]

#: Named methods as :class:`~gsw.mark.embed.EmbedConfig` overrides (``"weights"`` overrides single fields of
#: :class:`~gsw.mark.loss.LossWeights`). The two baselines are the prior methods ported to this embedder: no FGD
#: and no wavelet-subband loss, with StegaNeRF's magnitude mask (no exponential) or no mask (WateRF).
#: ``3d-gsw+attacks`` decodes an attacked copy of the render at half of the fine-tuning steps;
#: ``3d-gsw+all-attacks`` also decodes the render of a perturbed model (parameter noise or SH degree 0) at
#: half of them (``EmbedConfig.model_attacks``).
METHODS: dict[str, dict[str, Any]] = {
    "3d-gsw": {},
    "no-fgd": {"fgd": False},
    "no-mask": {"mask": "none"},
    "no-subband": {"weights": {"subband": 0.0}},
    "stega-3dgs": {"fgd": False, "mask": "stega", "weights": {"subband": 0.0}},
    "waterf-3dgs": {"fgd": False, "mask": "none", "weights": {"subband": 0.0}},
    "3d-gsw+attacks": {"attacks": 0.5},
    "3d-gsw+all-attacks": {"attacks": 0.5, "model_attacks": 0.5},
}

#: Rows of the ablation table: the full method and one component off at a time.
ABLATIONS: tuple[str, ...] = ("3d-gsw", "no-fgd", "no-mask", "no-subband")

#: The paper's model attacks (Gaussian noise on the parameters, remove 20 %, clone 20 %).
PAPER_MODEL_ATTACKS: tuple[str, ...] = ("parameter_noise", "remove", "clone")

#: EmbedConfig fields set by the grid itself (a grid axis or the scene), not by overrides.
_GRID_FIELDS = frozenset({"epochs", "seed", "background"})
_LPIPS_NETS = (None, "vgg", "alex")
#: Version of the cell / grid file layout.
FORMAT = 1


class GridMismatchError(ValueError):
    """The output folder holds a grid with other settings or another scene."""


# --------------------------------------------------------------------------------------------- methods


def apply_overrides(config: EmbedConfig, overrides: Mapping[str, Any]) -> EmbedConfig:
    """A copy of ``config`` with ``overrides`` applied.

    Args:
        config: the base configuration (not modified).
        overrides: EmbedConfig field -> value; ``"weights"`` maps LossWeights fields to values.

    Returns:
        A new :class:`EmbedConfig`.

    Raises:
        ValueError: an unknown field.
    """
    known = {f.name for f in dataclasses.fields(EmbedConfig)}
    unknown = set(overrides) - known
    if unknown:
        raise ValueError(f"unknown EmbedConfig fields {sorted(unknown)}; choose from {sorted(known)}")
    values = {k: v for k, v in overrides.items() if k != "weights"}
    if "background" in values:
        values["background"] = tuple(values["background"])
    if "weights" in overrides:
        weights = overrides["weights"]
        loss_fields = {f.name for f in dataclasses.fields(config.weights)}
        if set(weights) - loss_fields:
            raise ValueError(f"unknown LossWeights fields {sorted(set(weights) - loss_fields)}; choose from "
                             f"{sorted(loss_fields)}")
        values["weights"] = dataclasses.replace(config.weights, **weights)
    return dataclasses.replace(config, **values)


def lpips_loss_overrides(net: str | None) -> dict[str, Any]:
    """EmbedConfig overrides for the LPIPS term of the embedding loss.

    Args:
        net: ``"vgg"`` or ``"alex"``, or None to drop the term (network off and weight 0).

    Returns:
        Overrides for :attr:`GridSpec.embed`.
    """
    return {"lpips_net": net} if net else {"lpips_net": None, "weights": {"lpips": lpips_weights(None).lpips}}


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


# --------------------------------------------------------------------------------------------- spec


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
        image_attacks: keys of :data:`gsw.attacks.presets.IMAGE_ATTACKS` (the paper's strengths).
        model_attacks: keys of :data:`gsw.attacks.presets.MODEL_ATTACKS` or :data:`gsw.attacks.presets.VIEW_MODEL_ATTACKS`
            (``finetune`` trains on renders of the embedding views).
        sweeps: keys of :data:`gsw.attacks.presets.SWEEPS`: robustness curves over their values.
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
    model_attacks: tuple[str, ...] = PAPER_MODEL_ATTACKS
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
            if cfg.weights != lpips_weights(cfg.lpips_net, cfg.weights):
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


# --------------------------------------------------------------------------------------------- scenes


@dataclass
class GridScene:
    """A model to watermark and its views.

    Attributes:
        gaussians: the original model.
        cameras: embedding (training) views.
        eval_cameras: held-out evaluation views.
        images: ``[V, 3, H, W]`` training images for FGD phase 1, or None.
        background: RGB render background.
        key: JSON identity of the scene (stored in ``grid.json``).
    """

    gaussians: Gaussians
    cameras: list[Camera]
    eval_cameras: list[Camera]
    images: Tensor | None
    background: tuple[float, float, float]
    key: dict[str, Any]

    def __post_init__(self) -> None:
        if not self.cameras or not self.eval_cameras:
            raise ValueError("a grid scene needs training and evaluation views")

    def to(self, device: torch.device | str) -> "GridScene":
        """The same scene with its Gaussians and images on `device` (cameras stay plain data)."""
        return dataclasses.replace(self, gaussians=self.gaussians.to(device),
                                   images=None if self.images is None else self.images.to(device))


def _first(items: Sequence, n: int | None, what: str) -> list:
    if n is not None and not 0 < n <= len(items):  # n = None: all
        raise ValueError(f"{what} must be in 1..{len(items)}, got {n}")
    return list(items[:n])


def _spread(n_items: int, n: int | None, what: str) -> list[int]:
    """``n`` evenly spaced indices of ``n_items`` (all when ``n`` is None)."""
    if n is None:
        return list(range(n_items))
    if not 0 < n <= n_items:
        raise ValueError(f"{what} must be in 1..{n_items}, got {n}")
    return [i * n_items // n for i in range(n)]


def default_grid_scene(size: int = 64, views: int = 24, *, eval_views: int | None = None,
                       detail: float = 1.0) -> GridScene:
    """The built-in scene (:func:`gsw.scenes.default_scene`, white background).

    Args:
        size: render width and height, pixels.
        views: embedding views (an orbit).
        eval_views: evaluation views: the first of the orbit shifted by half a step (default: ``views``).
        detail: Gaussian density factor.

    Returns:
        A :class:`GridScene` without images.
    """
    from gsw.scenes import default_cameras, default_scene

    scene = default_scene(width=size, height=size, n_cameras=views, detail=detail)
    held_out = default_cameras(views, size, size, azimuth_offset_deg=180.0 / views)
    held_out = _first(held_out, eval_views, "eval_views")
    bg = tuple(float(v) for v in scene.background)
    key = dict(kind="default", size=size, views=views, eval_views=len(held_out), detail=detail)
    return GridScene(scene.gaussians, scene.cameras, held_out, None, bg, key)


def load_grid_scene(model: str | Path, data: str | Path | None = None, *, downscale: float = 1.0,
                    white: bool = False, holdout_every: int = 8, train_views: int | None = None,
                    eval_views: int | None = None) -> GridScene:
    """An INRIA model folder and, optionally, its dataset.

    With ``data`` (NeRF-synthetic or instant-ngp, :func:`gsw.data.load_dataset`) the ``train`` split gives
    the embedding views and images and the ``test`` split the evaluation views; without it the model's
    ``cameras.json`` is split, every ``holdout_every``-th view held out (no images: FGD phase 1 then weighs
    the renders).

    Args:
        model: the INRIA model folder.
        data: its dataset, or None.
        downscale: image / camera size divisor.
        white: white background (NeRF-synthetic), else black.
        holdout_every: hold-out period where the data has no test split.
        train_views: use this many evenly spaced embedding views (default: all).
        eval_views: use the first this many evaluation views (default: all).

    Returns:
        A :class:`GridScene`.
    """
    from gsw.data import holdout_indices, load_dataset, load_inria_model

    bg = (1.0, 1.0, 1.0) if white else (0.0, 0.0, 0.0)
    m = load_inria_model(model, downscale=downscale)
    if data is None:
        train_idx, test_idx = holdout_indices(len(m.cameras), holdout_every)
        cams, held_out, images = [m.cameras[i] for i in train_idx], [m.cameras[i] for i in test_idx], None
    else:
        kw = dict(downscale=downscale, background=bg, holdout_every=holdout_every)
        train, test = load_dataset(data, "train", **kw), load_dataset(data, "test", **kw)
        cams, held_out, images = train.cameras, test.cameras, train.images
    idx = _spread(len(cams), train_views, "train_views")
    held_out = _first(held_out, eval_views, "eval_views")
    key = dict(kind="inria", model=str(Path(model).resolve()), data=None if data is None else str(Path(data).resolve()),
               downscale=downscale, white=white, holdout_every=holdout_every, train_views=len(idx),
               eval_views=len(held_out))
    return GridScene(m.gaussians, [cams[i] for i in idx], held_out, None if images is None else images[idx], bg,
                     key)


# --------------------------------------------------------------------------------------------- detection


def detection_rate(p_values: Sequence[float], fpr: float) -> float:
    """Share of views whose p-value is at most ``fpr`` (the views detected at that false-positive rate).

    Args:
        p_values: per-view p-values.
        fpr: the false-positive rate of the test.

    Returns:
        A fraction in [0, 1] (0 for no views).
    """
    return sum(p <= fpr for p in p_values) / len(p_values) if p_values else 0.0


def detection_rates(report: Mapping[str, Any], fpr: float) -> dict[str, Any]:
    """TPR (watermarked views) and empirical FPR (original model's views), clean and per attack.

    Args:
        report: :meth:`gsw.eval.report.EvaluationReport.to_dict` of an evaluation with ``attack_unmarked``.
        fpr: the false-positive rate of the test.

    Returns:
        ``{"clean": {"tpr", "fpr"}, "image": {attack: {"tpr", "fpr"}}, "model": {attack: {...}}}``.
    """
    def pair(marked: Mapping, unmarked: Mapping) -> dict[str, float]:
        return {"tpr": detection_rate(marked["p_values"], fpr), "fpr": detection_rate(unmarked["p_values"], fpr)}

    out: dict[str, Any] = {"clean": pair(report["clean"], report["unmarked"])}
    for kind in ("image", "model"):
        unmarked = report[f"unmarked_{kind}_attacks"]
        out[kind] = {name: pair(d, unmarked[name]) for name, d in report[f"{kind}_attacks"].items()}
    return out


# --------------------------------------------------------------------------------------------- one cell


def _sweep_key(name: str, value: float) -> str:
    return f"{name}@{value:g}"


def _image_attacks(spec: GridSpec) -> dict[str, Callable[[Tensor], Tensor]]:
    """The spec's image attacks plus one per sweep value (named ``<attack>@<value>``)."""
    attacks = {name: IMAGE_ATTACKS[name] for name in spec.image_attacks}
    for name in spec.sweeps:
        parameter, values = SWEEPS[name]
        attacks.update({_sweep_key(name, v): partial(IMAGE_ATTACKS[name], **{parameter: v}) for v in values})
    return attacks


def _split_sweeps(report: dict[str, Any], spec: GridSpec) -> dict[str, Any]:
    """Moves the sweep entries out of ``report``'s image-attack tables; returns them per attack."""
    sweeps = {}
    for name in spec.sweeps:
        parameter, values = SWEEPS[name]
        keys = [_sweep_key(name, v) for v in values]
        sweeps[name] = {"parameter": parameter, "values": list(values),
                        "watermarked": [report["image_attacks"].pop(k) for k in keys],
                        "unmarked": [report["unmarked_image_attacks"].pop(k) for k in keys]}
    return sweeps


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@torch.no_grad()
def _fps(g: Gaussians, cameras: Sequence[Camera], background: Sequence[float], repeats: int) -> float:
    """Renders per second over ``cameras`` (after one warm-up render)."""
    rasterize(g, cameras[0], background=background)
    _sync(g.device)
    start = time.perf_counter()
    for _ in range(repeats):
        for cam in cameras:
            rasterize(g, cam, background=background, validate=False)
    _sync(g.device)
    return repeats * len(cameras) / (time.perf_counter() - start)


def _storage(g: Gaussians) -> dict[str, int]:
    """Gaussian count and size of the model as an INRIA PLY file."""
    from gsw.io import save_ply

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "point_cloud.ply"
        save_ply(g, path)
        return {"gaussians": len(g), "ply_bytes": path.stat().st_size}


def _first_view(g: Gaussians, scene: GridScene) -> Tensor:
    with torch.no_grad():
        return rasterize(g, scene.eval_cameras[0], background=scene.background).image.clamp(0, 1)


def run_cell(spec: GridSpec, scene: GridScene, cell: Cell, *, decoder: torch.nn.Module,
             original_storage: Mapping[str, int], image_path: Path | None = None) -> dict[str, Any]:
    """Embeds and evaluates one cell.

    Args:
        spec: the grid.
        scene: the model and its views.
        cell: which method, bit length and seed.
        decoder: the frozen decoder for ``cell.bits``.
        original_storage: Gaussian count and PLY bytes of the original model (computed once per grid).
        image_path: where to write the watermarked render of the first evaluation view (PNG), or None.

    Returns:
        The cell record (JSON-able): ``method``, ``bits``, ``seed``, ``config`` (the EmbedConfig),
        ``message`` (bits), ``report`` (the evaluation without the sweeps), ``sweeps`` (per sweep attack:
        ``parameter``, ``values`` and the detections of the watermarked and the original model per value),
        ``detection`` (:func:`detection_rates`), ``embedding`` (training-view bit accuracy / PSNR, FGD
        counts), ``timings`` (seconds: the embedder's phases and ``evaluation``), ``fps`` and ``storage``
        (``original`` / ``watermarked``).
    """
    cfg = spec.config(cell.method, cell.seed, scene.background)
    res = embed(scene.gaussians, scene.cameras, num_bits=cell.bits,
                images=None if scene.images is None else list(scene.images), config=cfg, decoder=decoder,
                progress=False)
    start = time.perf_counter()
    report = evaluate_watermark(res.gaussians, scene.gaussians, scene.eval_cameras, res.message,
                                num_bits=cell.bits, background=scene.background, image_attacks=_image_attacks(spec),
                                model_attacks=bind_model_attacks(spec.model_attacks, scene.cameras, scene.background),
                                lpips_net=spec.lpips_net, decoder=decoder, attack_unmarked=True).to_dict()
    evaluation_s = time.perf_counter() - start
    sweeps = _split_sweeps(report, spec)
    if image_path is not None:
        from gsw.data.images import write_image

        write_image(image_path, _first_view(res.gaussians, scene))
    n = len(res.bit_accuracy)
    return {
        "format": FORMAT, "method": cell.method, "bits": cell.bits, "seed": cell.seed,
        "config": asdict(cfg), "message": [int(b) for b in res.message.tolist()],
        "report": report, "sweeps": sweeps, "detection": detection_rates(report, spec.fpr),
        "embedding": {"train_bit_accuracy": sum(res.bit_accuracy) / n, "train_psnr": sum(res.psnr) / n,
                      "pruned": res.prune.num_removed if res.prune else 0,
                      "split": res.split.num_split if res.split else 0},
        "timings": {**res.timings, "evaluation": evaluation_s},
        "fps": {"original": _fps(scene.gaussians, scene.eval_cameras, scene.background, spec.fps_repeats),
                "watermarked": _fps(res.gaussians, scene.eval_cameras, scene.background, spec.fps_repeats)},
        "storage": {"original": dict(original_storage), "watermarked": _storage(res.gaussians)},
    }


# --------------------------------------------------------------------------------------------- aggregation


@dataclass(frozen=True)
class Stat:
    """Mean and sample standard deviation (``n - 1``; 0 for one value) of ``n`` values."""

    mean: float
    std: float
    n: int


def mean_std(values: Sequence[float]) -> Stat:
    """:class:`Stat` of values (e.g. one metric over seeds).

    Args:
        values: at least one number.

    Returns:
        The mean, the sample standard deviation and the count.
    """
    n = len(values)
    if n == 0:
        raise ValueError("mean_std needs at least one value")
    mean = sum(values) / n
    if n == 1 or not math.isfinite(mean):
        return Stat(mean, 0.0 if n == 1 else float("nan"), n)
    return Stat(mean, math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)), n)


def cell_metrics(cell: Mapping[str, Any]) -> dict[str, float]:
    """The numbers of a cell record as a flat ``name -> value`` dict.

    Names: ``bit_acc``, ``tpr``, ``fpr``, ``unmarked_bit_acc``, ``psnr``, ``ssim``, ``lpips`` (when measured),
    ``image:<attack>:{bit_acc,tpr,fpr}``, ``model:<attack>:{bit_acc,tpr,fpr}``, ``sweep:<attack>:<value>``
    (bit accuracy), ``time:<phase>`` (seconds), ``fps:{original,watermarked}``,
    ``gaussians:{original,watermarked}``, ``ply_mb:{original,watermarked}``.

    Args:
        cell: a record of :func:`run_cell`.

    Returns:
        The flat metrics.
    """
    report, det = cell["report"], cell["detection"]
    m = {"bit_acc": report["clean"]["bit_accuracy"], **det["clean"],
         "unmarked_bit_acc": report["unmarked"]["bit_accuracy"], "psnr": report["psnr"], "ssim": report["ssim"]}
    if report["lpips"] is not None:
        m["lpips"] = report["lpips"]
    for kind in ("image", "model"):
        for name, d in report[f"{kind}_attacks"].items():
            m.update({f"{kind}:{name}:bit_acc": d["bit_accuracy"], f"{kind}:{name}:tpr": det[kind][name]["tpr"],
                      f"{kind}:{name}:fpr": det[kind][name]["fpr"]})
    for name, sweep in cell["sweeps"].items():
        for value, d in zip(sweep["values"], sweep["watermarked"]):
            m[f"sweep:{name}:{value:g}"] = d["bit_accuracy"]
    m.update({f"time:{k}": v for k, v in cell["timings"].items()})
    for which in ("original", "watermarked"):
        m[f"fps:{which}"] = cell["fps"][which]
        m[f"gaussians:{which}"] = cell["storage"][which]["gaussians"]
        m[f"ply_mb:{which}"] = cell["storage"][which]["ply_bytes"] / 2**20
    return m


def aggregate(cells: Iterable[tuple[str, int, Mapping[str, float]]]) -> dict[tuple[str, int], dict[str, Stat]]:
    """Mean +- std over seeds of every metric, per (method, bits).

    Args:
        cells: ``(method, bits, metrics)`` per cell (metrics as returned by :func:`cell_metrics`).

    Returns:
        ``{(method, bits): {metric: Stat}}`` in first-seen order; a metric missing from some cells is
        aggregated over the cells that have it.
    """
    values: dict[tuple[str, int], dict[str, list[float]]] = {}
    for method, bits, metrics in cells:
        group = values.setdefault((method, bits), {})
        for name, v in metrics.items():
            group.setdefault(name, []).append(float(v))
    return {key: {name: mean_std(vs) for name, vs in group.items()} for key, group in values.items()}


# --------------------------------------------------------------------------------------------- tables


#: A table column: (header, metric name, scale, decimals).
_Column = tuple[str, str, float, int]
_QUALITY: tuple[_Column, ...] = (("bit acc (%)", "bit_acc", 100.0, 2), ("PSNR", "psnr", 1.0, 2),
                                 ("SSIM", "ssim", 1.0, 4), ("LPIPS", "lpips", 1.0, 4))


def _fmt(stat: Stat | None, scale: float = 1.0, digits: int = 2, std: bool = True) -> str:
    """``mean ± std`` (just the mean for one value or ``std=False``; ``-`` when missing)."""
    if stat is None:
        return "-"
    text = f"{scale * stat.mean:.{digits}f}"
    return text if stat.n == 1 or not std else f"{text} ± {scale * stat.std:.{digits}f}"


def _table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header),
            *("| " + " | ".join(row) + " |" for row in rows)]


@dataclass
class GridSummary:
    """Aggregated grid: mean +- std over seeds per (method, bits), and the paper's tables.

    Attributes:
        spec: the grid.
        scene: the scene's key.
        groups: ``{(method, bits): {metric: Stat}}`` (metric names of :func:`cell_metrics`).
        computed: cells computed by this run.
        reused: cells read back from earlier runs.
    """

    spec: GridSpec
    scene: dict[str, Any]
    groups: dict[tuple[str, int], dict[str, Stat]]
    computed: int = 0
    reused: int = 0

    def stat(self, method: str, bits: int, metric: str) -> Stat | None:
        """One aggregated metric, or None when absent."""
        return self.groups.get((method, bits), {}).get(metric)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary."""
        return {"format": FORMAT, "methods": list(self.spec.methods), "bits": list(self.spec.bits),
                "seeds": list(self.spec.seeds), "report_bits": self.spec.report_bits,
                "settings": self.spec.settings(), "scene": self.scene,
                "computed": self.computed, "reused": self.reused,
                "groups": [{"method": m, "bits": b, "metrics": {k: asdict(s) for k, s in metrics.items()}}
                           for (m, b), metrics in self.groups.items()]}

    def _row(self, method: str, bits: int, columns: Sequence[_Column]) -> list[str]:
        return [_fmt(self.stat(method, bits, metric), scale, digits) for _, metric, scale, digits in columns]

    def _per_method(self, bits: int, columns: Sequence[_Column], methods: Sequence[str] | None = None) -> list[str]:
        """Rows = methods, one column per :data:`_Column`."""
        return _table(["method", *(c[0] for c in columns)],
                      ([m, *self._row(m, bits, columns)] for m in methods or self.spec.methods))

    def capacity_table(self) -> list[str]:
        """(a) Capacity: rows = methods, per bit length bit accuracy (%), PSNR, SSIM, LPIPS."""
        header = [f"{b} bits: {c[0]}" if i == 0 else c[0] for b in self.spec.bits for i, c in enumerate(_QUALITY)]
        return _table(["method", *header], ([m, *(v for b in self.spec.bits for v in self._row(m, b, _QUALITY))]
                                            for m in self.spec.methods))

    def robustness_table(self, kind: str) -> list[str]:
        """(b) image / (c) model attacks: rows = methods, bit accuracy (%) clean and per attack."""
        names = self.spec.image_attacks if kind == "image" else self.spec.model_attacks
        columns = [("none", "bit_acc", 100.0, 2), *((n, f"{kind}:{n}:bit_acc", 100.0, 2) for n in names)]
        return self._per_method(self.spec.report_bits, columns)

    def ablation_table(self) -> list[str]:
        """(d) Ablation: 3d-gsw and one component off, bit accuracy (%), PSNR, SSIM, LPIPS."""
        rows = [m for m in ABLATIONS if m in self.spec.methods]
        return self._per_method(self.spec.report_bits, _QUALITY, rows) if len(rows) > 1 else []

    def detection_table(self) -> list[str]:
        """TPR / empirical FPR (% of views, means over seeds) at :attr:`GridSpec.fpr`, clean and per attack."""
        attacks = [f"image:{n}" for n in self.spec.image_attacks] + [f"model:{n}" for n in self.spec.model_attacks]
        b = self.spec.report_bits

        def pair(m: str, prefix: str) -> str:
            tpr, fpr = (_fmt(self.stat(m, b, prefix + rate), 100.0, 0, std=False) for rate in ("tpr", "fpr"))
            return f"{tpr} / {fpr}"

        return _table(["method", "clean", *(a.split(":", 1)[1] for a in attacks)],
                      ([m, pair(m, ""), *(pair(m, f"{a}:") for a in attacks)] for m in self.spec.methods))

    def cost_table(self) -> list[str]:
        """(e) Time, render speed and storage per method and bit length."""
        def arrow(m: str, b: int, metric: str, scale: float, digits: int) -> str:
            return (f"{_fmt(self.stat(m, b, metric + ':original'), scale, digits)} -> "
                    f"{_fmt(self.stat(m, b, metric + ':watermarked'), scale, digits)}")

        rows = ([m, str(b), _fmt(self.stat(m, b, "time:fgd"), 1.0, 1), _fmt(self.stat(m, b, "time:finetune"), 1.0, 1),
                 _fmt(self.stat(m, b, "time:total"), 1.0, 1), arrow(m, b, "fps", 1.0, 1),
                 arrow(m, b, "gaussians", 1.0, 0), arrow(m, b, "ply_mb", 1.0, 2)]
                for m in self.spec.methods for b in self.spec.bits)
        return _table(["method", "bits", "FGD (s)", "fine-tune (s)", "embed total (s)", "FPS", "Gaussians",
                       "PLY (MB)"], rows)

    def sweep_tables(self) -> list[str]:
        """Robustness curves as tables: per sweep attack, rows = methods, bit accuracy (%) per strength."""
        lines: list[str] = []
        for name in self.spec.sweeps:
            parameter, values = SWEEPS[name]
            columns = [(f"{parameter}={v:g}", f"sweep:{name}:{v:g}", 100.0, 1) for v in values]
            lines += [f"### {name}", "", *self._per_method(self.spec.report_bits, columns), ""]
        return lines

    def to_markdown(self) -> str:
        """Every table, with a short caption each."""
        s, b = self.spec, self.spec.report_bits
        seeds = f"mean ± std over {len(s.seeds)} seeds" if len(s.seeds) > 1 else "one seed"
        parts = [
            ("Capacity: bit accuracy and invisibility (vs renders of the original model)", self.capacity_table()),
            (f"Image attacks: bit accuracy (%), {b} bits", self.robustness_table("image")),
            (f"Model attacks: bit accuracy (%), {b} bits", self.robustness_table("model")),
            (f"Ablation, {b} bits", self.ablation_table()),
            (f"Detection at FPR {s.fpr:g}: TPR / empirical FPR on the original model (% of views, mean), {b} bits",
             self.detection_table()),
            ("Time (s), render speed (FPS) and storage, original -> watermarked", self.cost_table()),
            (f"Robustness curves: bit accuracy (%) vs attack strength, {b} bits", self.sweep_tables()),
        ]
        lines = [f"# Evaluation grid ({seeds}; {self.scene.get('kind')} scene; epochs: {s.epochs})", ""]
        for caption, table in parts:
            if table:
                lines += [f"## {caption}", "", *table, ""]
        return "\n".join(lines).rstrip() + "\n"


# --------------------------------------------------------------------------------------------- runner


def _grid_record(spec: GridSpec, scene: GridScene) -> dict[str, Any]:
    return {"format": FORMAT, "settings": spec.settings(), "scene": json.loads(json.dumps(scene.key))}


def _digest(record: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()[:16]


def _write_json(path: Path, data: Any) -> None:
    with atomic_write(path, "w") as f:
        json.dump(data, f, indent=1)
        f.write("\n")


def _claim(out: Path, record: dict[str, Any], force: bool) -> None:
    """Creates the grid folder with its ``grid.json``, or checks that its grid has the same settings and scene."""
    path = out / "grid.json"
    if path.exists() and not force:
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            raise GridMismatchError(f"{path} is unreadable ({err}); pass --force to start the grid over") from None
        if old != record:
            diff = sorted(k for part in ("settings", "scene") for k in set(old.get(part, {})) | set(record[part])
                          if old.get(part, {}).get(k) != record[part].get(k))
            raise GridMismatchError(f"{out} holds a grid with other settings or scene (differs in {diff}); use "
                                    "another output folder, or --force to replace its settings")
        return
    if out.is_dir() and any(out.iterdir()) and not force:
        raise GridMismatchError(f"{out} is not empty and holds no grid.json; use a new folder, or --force to use it")
    out.mkdir(parents=True, exist_ok=True)
    _write_json(path, record)


_CELL_KEYS = ("format", "grid", "method", "bits", "seed", "config", "message", "report", "sweeps", "detection",
              "embedding", "timings", "fps", "storage")


def decoder_fingerprint(decoder: torch.nn.Module) -> str:
    """Short sha256 of a decoder's parameters and buffers (names, dtypes, shapes, values)."""
    h = hashlib.sha256()
    for name, t in sorted(decoder.state_dict().items()):
        t = t.detach().cpu().contiguous()
        h.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()[:16]


def _load_cell(path: Path, cell: Cell, digest: str, config: dict[str, Any],
               decoder: str) -> dict[str, Any] | None:
    """A finished cell of this grid, or None (missing, corrupt, or from other settings, another resolved
    EmbedConfig (e.g. changed library defaults) or another decoder: recompute)."""
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        complete = isinstance(data, dict) and all(k in data for k in _CELL_KEYS)
    except (OSError, ValueError):
        complete = False
    if not complete or (data["method"], data["bits"], data["seed"]) != tuple(cell) or data["format"] != FORMAT:
        warnings.warn(f"{path} is corrupt or incomplete; recomputing the cell", RuntimeWarning, stacklevel=3)
        return None
    if data["grid"] != digest or json.loads(json.dumps(data["config"])) != json.loads(json.dumps(config)):
        warnings.warn(f"{path} was computed with other settings; recomputing the cell", RuntimeWarning,
                      stacklevel=3)
        return None
    if data.get("decoder") != decoder:
        warnings.warn(f"{path} was computed with another decoder; recomputing the cell", RuntimeWarning,
                      stacklevel=3)
        return None
    return data


def _default_decoder(bits: int) -> torch.nn.Module:
    from gsw.decoder.zoo import load_decoder

    return load_decoder(bits)


def run_grid(spec: GridSpec, scene: GridScene, output: str | Path, *, resume: bool = True, force: bool = False,
             progress: bool = True,
             decoder_for: Callable[[int], torch.nn.Module] = _default_decoder) -> GridSummary:
    """Runs (or resumes) a grid and writes its cells and summary into ``output``.

    Args:
        spec: the grid.
        scene: the model and its views.
        output: the grid folder (created; an existing one must hold this grid, or be empty).
        resume: keep the finished cells of an earlier run (recomputing corrupt ones); False recomputes all.
        force: replace the settings of a folder that holds another grid (its cells are recomputed).
        progress: show a progress bar over the cells on stderr.
        decoder_for: bit length -> frozen decoder (default: the shipped ones), loaded once per bit length.
            A finished cell is reused only if its decoder (parameter fingerprint) and its resolved
            EmbedConfig are the current ones.

    Returns:
        The :class:`GridSummary` of the spec's cells (also written as ``summary.json`` / ``summary.md``).

    Raises:
        GridMismatchError: ``output`` holds a grid with other settings or another scene, or other files
            (and not ``force``).
    """
    out = Path(output)
    record = _grid_record(spec, scene)
    _claim(out, record, force)
    (out / "cells").mkdir(exist_ok=True)
    digest = _digest(record)
    from gsw.data.images import write_image

    write_image(out / "original.png", _first_view(scene.gaussians, scene))
    decoders = {bits: decoder_for(bits) for bits in spec.bits}
    fingerprints = {bits: decoder_fingerprint(d) for bits, d in decoders.items()}
    original_storage: dict[str, int] | None = None
    cells, computed = [], 0
    with Progress(len(spec.cells()), "grid", enabled=progress) as bar:
        for cell in spec.cells():
            path = out / "cells" / f"{cell.name}.json"
            config = asdict(spec.config(cell.method, cell.seed, scene.background))
            data = _load_cell(path, cell, digest, config, fingerprints[cell.bits]) if resume else None
            if data is None:
                original_storage = original_storage or _storage(scene.gaussians)
                data = {"grid": digest, "decoder": fingerprints[cell.bits],
                        **run_cell(spec, scene, cell, decoder=decoders[cell.bits], original_storage=original_storage,
                                   image_path=path.with_suffix(".png"))}
                _write_json(path, data)
                computed += 1
            cells.append(data)
            bar.update(cell=cell.name, acc=f"{100 * data['report']['clean']['bit_accuracy']:.1f}%")
    groups = aggregate((c["method"], c["bits"], cell_metrics(c)) for c in cells)
    summary = GridSummary(spec, record["scene"], groups, computed, len(cells) - computed)
    _write_json(out / "summary.json", summary.to_dict())
    with atomic_write(out / "summary.md", "w") as f:
        f.write(summary.to_markdown())
    return summary
