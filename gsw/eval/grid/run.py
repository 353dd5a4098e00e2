"""Running a grid: one cell (:func:`run_cell`: embed, evaluate, time, size) and the resumable grid
(:func:`run_grid`)."""

from __future__ import annotations

import tempfile
import time
from dataclasses import asdict
from functools import partial
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch
from torch import Tensor

from gsw._atomic import atomic_write
from gsw.attacks.presets import IMAGE_ATTACKS, SWEEPS, bind_model_attacks
from gsw.camera import Camera
from gsw.eval.grid.scene import GridScene
from gsw.eval.grid.spec import FORMAT, Cell, GridSpec
from gsw.eval.grid.store import _claim, _default_decoder, _digest, _grid_record, _load_cell, _write_json, \
    decoder_fingerprint, legacy_decoder_fingerprint
from gsw.eval.grid.summary import GridSummary, aggregate, cell_metrics, detection_rates
from gsw.eval.report import evaluate_watermark
from gsw.gaussians import Gaussians
from gsw.mark.embed import embed
from gsw.mark.message import random_message
from gsw.progress import Progress
from gsw.render.rasterize import rasterize

__all__ = ["run_cell", "run_grid"]


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
    message = random_message(cell.bits, seed=cfg.seed)  # seeded (public): grid cells are reproducible
    res = embed(scene.gaussians, scene.cameras, message=message, num_bits=cell.bits,
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
    fingerprints = {bits: (decoder_fingerprint(d), legacy_decoder_fingerprint(d)) for bits, d in decoders.items()}
    original_storage: dict[str, int] | None = None
    cells, computed = [], 0
    with Progress(len(spec.cells()), "grid", enabled=progress) as bar:
        for cell in spec.cells():
            path = out / "cells" / f"{cell.name}.json"
            config = asdict(spec.config(cell.method, cell.seed, scene.background))
            data = _load_cell(path, cell, digest, config, fingerprints[cell.bits]) if resume else None
            if data is None:
                original_storage = original_storage or _storage(scene.gaussians)
                data = {"grid": digest, "decoder": fingerprints[cell.bits][0],
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
