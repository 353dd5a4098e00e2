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

from gsw.eval.grid.run import run_cell, run_grid
from gsw.eval.grid.scene import GridScene, default_grid_scene, load_grid_scene
from gsw.eval.grid.spec import (ABLATIONS, FORMAT, METHODS, PAPER_MODEL_ATTACKS, Cell, GridMismatchError, GridSpec,
                                apply_overrides, lpips_loss_overrides, method_config)
from gsw.eval.grid.store import decoder_fingerprint
from gsw.eval.grid.summary import GridSummary, Stat, aggregate, cell_metrics, detection_rate, detection_rates, mean_std

__all__ = [
    "METHODS", "ABLATIONS", "PAPER_MODEL_ATTACKS", "FORMAT", "GridSpec", "GridScene", "Cell", "Stat", "GridSummary",
    "GridMismatchError", "method_config", "apply_overrides", "lpips_loss_overrides", "default_grid_scene",
    "load_grid_scene", "detection_rate", "detection_rates", "mean_std", "cell_metrics", "aggregate", "run_cell",
    "run_grid", "decoder_fingerprint",
]
