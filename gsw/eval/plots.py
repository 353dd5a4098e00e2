"""Figures of an evaluation grid (:mod:`gsw.grid`): robustness curves and difference maps.

matplotlib is optional and not a dependency of gsw: install it with ``pip install matplotlib`` (or the
``plots`` extra, ``pip install 'gsw[plots]'``). It is imported only when a figure is drawn, through its
object-oriented API (no pyplot, no global backend change).

Example:
    >>> from gsw.plots import plot_grid
    >>> plot_grid("eval-grid")  # doctest: +SKIP
    [PosixPath('eval-grid/plots/robustness.png'), PosixPath('eval-grid/plots/difference_maps.png')]
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

from gsw._atomic import atomic_write
from gsw.attacks.presets import SWEEPS

__all__ = ["require_matplotlib", "plot_robustness", "plot_difference_maps", "plot_grid"]

#: Difference maps are ``|watermarked - original|`` times this factor.
DIFFERENCE_GAIN = 2.0


def require_matplotlib() -> type:
    """matplotlib's ``Figure`` class, or a clear error when matplotlib is not installed.

    Returns:
        ``matplotlib.figure.Figure``.

    Raises:
        ImportError: matplotlib is missing (the message says how to install it).
    """
    try:
        from matplotlib.figure import Figure
    except ImportError as err:
        raise ImportError("plots need matplotlib, which gsw does not install: pip install matplotlib "
                          "(or pip install 'gsw[plots]')") from err
    return Figure


def _save(fig: Any, path: str | Path) -> Path:
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format="png", dpi=120)
    return Path(path)


def _metric(summary: Mapping[str, Any], method: str, bits: int, name: str) -> dict[str, float] | None:
    for group in summary["groups"]:
        if group["method"] == method and group["bits"] == bits:
            return group["metrics"].get(name)
    return None


def plot_robustness(summary: Mapping[str, Any], path: str | Path) -> Path:
    """Bit accuracy vs attack strength, one panel per sweep attack, one line (mean +- std) per method.

    Args:
        summary: ``summary.json`` of a grid (:meth:`gsw.eval.grid.GridSummary.to_dict`).
        path: the PNG to write.

    Returns:
        ``path``.
    """
    figure_cls = require_matplotlib()
    sweeps, bits = summary["settings"]["sweeps"], summary["report_bits"]
    if not sweeps:
        raise ValueError("the grid has no sweeps (GridSpec.sweeps) to plot")
    fig = figure_cls(figsize=(4.0 * len(sweeps), 3.4), layout="constrained")
    for ax, name in zip(fig.subplots(1, len(sweeps), squeeze=False)[0], sweeps):
        parameter, values = SWEEPS[name]
        for method in summary["methods"]:
            stats = [_metric(summary, method, bits, f"sweep:{name}:{v:g}") for v in values]
            xs = [v for v, st in zip(values, stats) if st is not None]
            ys = [100 * st["mean"] for st in stats if st is not None]
            errs = [100 * st["std"] for st in stats if st is not None]
            ax.errorbar(xs, ys, yerr=errs, marker="o", markersize=3, capsize=2, label=method)
        ax.set(title=name, xlabel=parameter, ylabel=f"bit accuracy (%), {bits} bits", ylim=(0, 101))
        ax.axhline(50, color="grey", linewidth=0.8, linestyle=":")
    fig.axes[0].legend(fontsize="small")
    return _save(fig, path)


def plot_difference_maps(grid_dir: str | Path, summary: Mapping[str, Any], path: str | Path) -> Path:
    """The original render, each method's watermarked render and ``|difference| x 2`` (first evaluation view).

    Uses the first seed at the report bit length (``original.png`` and ``cells/<cell>.png`` of the grid).

    Args:
        grid_dir: the grid folder.
        summary: its ``summary.json``.
        path: the PNG to write.

    Returns:
        ``path``.
    """
    from gsw.data.images import read_image
    from gsw.eval.grid import Cell

    figure_cls = require_matplotlib()
    grid_dir = Path(grid_dir)
    original = read_image(grid_dir / "original.png")[:3]
    methods, bits, seed = summary["methods"], summary["report_bits"], summary["seeds"][0]
    fig = figure_cls(figsize=(2.4 * (len(methods) + 1), 5.0), layout="constrained")
    axes = fig.subplots(2, len(methods) + 1, squeeze=False)
    for ax in axes.flat:
        ax.set_axis_off()
    axes[0, 0].imshow(original.permute(1, 2, 0).numpy())
    axes[0, 0].set_title("original", fontsize="small")
    for col, method in enumerate(methods, start=1):
        marked = read_image(grid_dir / "cells" / f"{Cell(method, bits, seed).name}.png")[:3]
        diff = ((marked - original).abs() * DIFFERENCE_GAIN).clamp(0, 1)
        axes[0, col].imshow(marked.permute(1, 2, 0).numpy())
        axes[0, col].set_title(method, fontsize="small")
        axes[1, col].imshow(diff.permute(1, 2, 0).numpy())
        axes[1, col].set_title(f"|difference| x {DIFFERENCE_GAIN:g}", fontsize="small")
    return _save(fig, path)


def plot_grid(grid_dir: str | Path) -> list[Path]:
    """Draws the figures of a finished grid into ``<grid_dir>/plots/``.

    Args:
        grid_dir: a folder written by :func:`gsw.eval.grid.run_grid`.

    Returns:
        The PNGs written: ``robustness.png`` (when the grid has sweeps) and ``difference_maps.png``.
    """
    require_matplotlib()
    grid_dir = Path(grid_dir)
    summary = json.loads((grid_dir / "summary.json").read_text(encoding="utf-8"))
    out = grid_dir / "plots"
    out.mkdir(exist_ok=True)
    written = [plot_robustness(summary, out / "robustness.png")] if summary["settings"]["sweeps"] else []
    return written + [plot_difference_maps(grid_dir, summary, out / "difference_maps.png")]
