"""Grid results: detection rates at an FPR, mean +- std over seeds (:class:`Stat`) and the paper's tables
(:class:`GridSummary`)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Iterable, Mapping, Sequence

from gsw.attacks.presets import SWEEPS
from gsw.eval.grid.spec import ABLATIONS, FORMAT, GridSpec

__all__ = ["GridSummary", "Stat", "aggregate", "cell_metrics", "detection_rate", "detection_rates", "mean_std"]


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
